"""Inference-only rewrites of zoo networks for export (same function, cheaper graph).

``inference_copy(net)`` returns an eval-mode deep copy in which

- spectrally normalised linears become plain ``nn.Linear`` with the normalised weight (eval-mode
  arithmetic: the stored ``u``/``v``, no power iteration);
- grouped convolutions with few channels per group (the mix-FFN's 8) are embedded in convolutions with
  16 channels per group (block-diagonal weights, zeros off the blocks), which ONNX Runtime runs in its
  blocked-channel (NCHWc) kernels, faster than the exact grouping despite the zero products;
- the mix-FFN runs as 1x1 convolution -> grouped convolution -> GELU -> 1x1 convolution on a
  channels-last view of the tokens, which ONNX Runtime keeps in its blocked layout from end to end
  instead of reordering the widest tensor twice;
- the efficient self-attention has the 1/sqrt(d) scale folded into the query weights and the output
  projection folded into the value projection (attention rows sum to one), one product less per layer;
- LSTMs run as their cell equations written out (``lstm_inference``): at batch 1 a handful of small
  products beat ONNX Runtime's LSTM kernel several times over;
- in the ViT, the decoder Linear and the first head Linear (nothing non-linear between them) are folded
  into one smaller product; in the ViT+LSTM the decoder is folded into the LSTM's first input product;
- in the ConvNet (batch-norm scales all positive, as trained ones are), batch norm and the min-pool's
  negations go into the convolutions, the average pool into fc0, the 0.1 speed scale into fc0's speed
  column, and the head runs on 2-D rows (``_FoldedConvNet``);
- where the state (speed, attitude) is concatenated to the image features (ConvNet's fc0, the LSTMnet's and
  UNet+LSTM's first LSTM input), it enters through a product of its own (``StateSplitLSTM``), so the int8
  path can keep it float32 and give the image weights their own scales.

The original network is left untouched; the export checks the copy against it.
"""

from __future__ import annotations

import copy

import torch
import torch.nn.functional as F
from torch import nn

from vitfly.zoo.convnet import ConvNet
from vitfly.zoo.layers import SPEED_SCALE, STATE_DIM, SNLinear
from vitfly.zoo.lstmnet import LSTMNet
from vitfly.zoo.mix_transformer import EfficientSelfAttention, MixFFN
from vitfly.zoo.recurrent import lstm_inference
from vitfly.zoo.unet_lstm import UNetLSTM
from vitfly.zoo.vit import ViT
from vitfly.zoo.vit_lstm import ViTLSTM

# ONNX Runtime's blocked convolution kernels need channel counts per group in multiples of this
CHANNEL_BLOCK = 16


def plain_linear(layer: SNLinear) -> nn.Linear:
    """An ``nn.Linear`` holding the eval-mode normalised weight of ``layer``."""
    with torch.no_grad():
        training = layer.training
        layer.eval()  # eval-mode arithmetic: stored u and v, no power-iteration update
        weight = layer._normalised_weight()
        layer.train(training)
        out = nn.Linear(layer.in_features, layer.out_features, bias=layer.bias is not None)
        out.weight.copy_(weight)
        if layer.bias is not None:
            out.bias.copy_(layer.bias)
    return out


def merge_conv_groups(conv: nn.Conv2d, block: int = CHANNEL_BLOCK) -> nn.Conv2d:
    """Same convolution with groups merged so each group has a multiple of ``block`` channels.

    Returns ``conv`` itself when it is dense, depthwise, or cannot be merged evenly.
    """
    groups = conv.groups
    in_per, out_per = conv.in_channels // groups, conv.out_channels // groups
    if groups == 1 or in_per == 1 or in_per % block == 0 or in_per != out_per:
        return conv
    merge = block // in_per if block % in_per == 0 else 0
    if merge < 2 or groups % merge:
        return conv
    new_groups = groups // merge
    merged = nn.Conv2d(
        conv.in_channels, conv.out_channels, conv.kernel_size, conv.stride, conv.padding, conv.dilation,
        groups=new_groups, bias=conv.bias is not None, padding_mode=conv.padding_mode,
    )  # fmt: skip
    with torch.no_grad():
        weight = torch.zeros_like(merged.weight)  # (out, in_per * merge, kh, kw)
        for out_channel in range(conv.out_channels):
            slot = (out_channel // out_per) % merge  # position of the original group inside the merged one
            weight[out_channel, slot * in_per : (slot + 1) * in_per] = conv.weight[out_channel]
        merged.weight.copy_(weight)
        if conv.bias is not None:
            merged.bias.copy_(conv.bias)
    return merged


def _pointwise_conv(linear: nn.Linear) -> nn.Conv2d:
    conv = nn.Conv2d(linear.in_features, linear.out_features, kernel_size=1)
    with torch.no_grad():
        conv.weight.copy_(linear.weight[:, :, None, None])
        conv.bias.copy_(linear.bias)
    return conv


class ConvMixFFN(nn.Module):
    """``MixFFN`` as convolutions on the channels-last token grid (same call: tokens (N, H*W, C), h, w)."""

    def __init__(self, ffn: MixFFN, gelu: str = "none") -> None:
        super().__init__()
        self.gelu = gelu  # F.gelu's ``approximate``: "none" (exact, erf) or "tanh"
        self.mlp1 = _pointwise_conv(ffn.mlp1)
        self.depthwise = merge_conv_groups(ffn.depthwise)
        self.mlp2 = _pointwise_conv(ffn.mlp2)

    def forward(self, x: torch.Tensor, h: int, w: int) -> torch.Tensor:
        c = x.shape[-1]
        grid = x.reshape(-1, h, w, c).permute(0, 3, 1, 2)  # a view: ORT reads it straight into its blocked layout
        y = self.mlp2(F.gelu(self.depthwise(self.mlp1(grid)), approximate=self.gelu))
        return y.permute(0, 2, 3, 1).reshape(-1, h * w, c)


class FusedConvMixFFN(nn.Module):
    """``MixFFN`` with mlp1 multiplied into the grouped convolution: one dense 3x3 convolution C -> C*E.

    Nothing non-linear sits between mlp1 and the grouped convolution, so per output channel o of group g
    the pair is ``sum_taps W_g[tap] @ W1_g`` applied to the shifted tokens: a dense convolution of the
    C-channel token grid. It has more products than the pair (C*9 per output against 1 + E*9), but it is
    the shape int8 convolution kernels run fastest (``vitfly.deploy.quantize``: about 3x the float pair).
    mlp1's bias goes through the grouped convolution's zero padding, so border pixels see fewer taps of it:
    it rides on an extra input channel of ones (zero-padded like the rest, so the border sees exactly the
    taps it should), plus three zero channels: the int8 kernel wants input channels in multiples of 4.
    Tokens stay channels-last. ``gelu`` "quick" takes GELU's sigmoid approximation ``x * sigmoid(1.702 x)``
    (a different function, for int8 chains that stay uint8 from the convolution to mlp2; ``QUICK_GELU``) and
    runs mlp2 as a 1x1 convolution (``fused_mlp2``) on the same grid.
    """

    EXTRA_CHANNELS = 4  # [ones, 0, 0, 0]

    def __init__(self, ffn: MixFFN, gelu: str = "none") -> None:
        super().__init__()
        self.gelu = gelu
        depthwise = ffn.depthwise
        groups, hidden = depthwise.groups, depthwise.out_channels
        per_group = depthwise.in_channels // groups
        channels = ffn.mlp1.in_features
        with torch.no_grad():
            w1 = ffn.mlp1.weight.reshape(groups, per_group, channels)  # (groups, E in, C)
            wd = depthwise.weight.reshape(groups, per_group, per_group, 3, 3)  # (groups, E out, E in, 3, 3)
            b1 = ffn.mlp1.bias.reshape(groups, per_group)
            weight = torch.zeros(hidden, channels + self.EXTRA_CHANNELS, 3, 3)
            weight[:, :channels] = torch.einsum("goiyx,gic->gocyx", wd, w1).reshape(hidden, channels, 3, 3)
            weight[:, channels] = torch.einsum("goiyx,gi->goyx", wd, b1).reshape(hidden, 3, 3)
            self.fused_conv = nn.Conv2d(channels + self.EXTRA_CHANNELS, hidden, kernel_size=3, padding=1)
            self.fused_conv.weight.copy_(weight)
            self.fused_conv.bias.copy_(depthwise.bias)
        extra = torch.zeros(1, 1, 1, self.EXTRA_CHANNELS)
        extra[..., 0] = 1.0
        self.register_buffer("extra", extra)
        self.mlp2 = ffn.mlp2
        if gelu == "quick":  # mlp2 as a 1x1 convolution on the same grid: the uint8 chain stays channels-last
            self.fused_mlp2 = _pointwise_conv(ffn.mlp2)

    def forward(self, x: torch.Tensor, h: int, w: int) -> torch.Tensor:
        n, length, c = x.shape
        grid = torch.cat((x.reshape(n, h, w, c), self.extra.expand(n, h, w, -1)), dim=-1)
        if self.gelu == "quick":
            y = self.fused_conv(grid.permute(0, 3, 1, 2))
            y = self.fused_mlp2(y * torch.sigmoid(QUICK_GELU * y))
            return y.permute(0, 2, 3, 1).reshape(n, length, c)
        y = self.fused_conv(grid.permute(0, 3, 1, 2)).permute(0, 2, 3, 1)
        return self.mlp2(F.gelu(y, approximate=self.gelu).reshape(n, length, -1))


# GELU(x) ~ x * sigmoid(1.702 x) (|error| < 0.021): a sigmoid, which int8 kernels run as a 256-entry table
QUICK_GELU = 1.702
# the ViT stages whose int8 mix-FFNs take it. None: with the shipped trained ViT (weights/) it moved the commands
# over recorded flights by up to 0.38 m/s in both stages, 0.36 in stage 0 only, 0.13 in stage 1 only, against
# 0.11 with the float GELU (tolerance 0.15 m/s; benchmarks/fast_path_agreement.py)
QUICK_GELU_STAGES: dict[str, tuple[int, ...]] = {}


def fuse_mix_ffns(backbone: nn.Module, gelu: str = "tanh", quick_gelu_stages: tuple[int, ...] = ()) -> None:
    """Replace every mix-FFN of a ViT backbone (``encoder_blocks``) by ``FusedConvMixFFN``, in place; the
    stages in ``quick_gelu_stages`` take the sigmoid approximation of GELU (see ``FusedConvMixFFN``)."""
    for index, stage in enumerate(backbone.encoder_blocks):
        for i, ffn in enumerate(stage._ffn):
            stage._ffn[i] = FusedConvMixFFN(ffn, "quick" if index in quick_gelu_stages else gelu)


class FoldedAttention(nn.Module):
    """``EfficientSelfAttention`` with the query scale and the output projection folded in.

    out = sum_h softmax(q_h k_h^T / sqrt(d)) (v_h Wf_h^T + bf / heads), where Wf_h are the output
    projection's columns for head h; the per-head value projections are stacked so one product serves all
    heads.
    """

    def __init__(self, attn: EfficientSelfAttention) -> None:
        super().__init__()
        c = attn.query.in_features
        heads = attn.num_heads
        d = c // heads
        self.num_heads, self.head_dim, self.channels = heads, d, c
        self.cn1, self.ln1 = attn.cn1, attn.ln1
        with torch.no_grad():
            self.query = nn.Linear(c, c)
            self.query.weight.copy_(attn.query.weight / d**0.5)
            self.query.bias.copy_(attn.query.bias / d**0.5)
            self.key = nn.Linear(c, c)
            self.key.weight.copy_(attn.keyValueExtractor.weight[:c])
            self.key.bias.copy_(attn.keyValueExtractor.bias[:c])
            w_v, b_v = attn.keyValueExtractor.weight[c:], attn.keyValueExtractor.bias[c:]
            w_f = attn.finalLayer.weight
            self.value = nn.Linear(c, heads * c)  # head-major blocks of (C) outputs
            for head in range(heads):
                rows = slice(head * d, (head + 1) * d)
                self.value.weight[head * c : (head + 1) * c].copy_(w_f[:, rows] @ w_v[rows])
                # each head's attention rows sum to one, so the output bias splits over the heads' values
                bias = w_f[:, rows] @ b_v[rows] + attn.finalLayer.bias / heads
                self.value.bias[head * c : (head + 1) * c].copy_(bias)

    def forward(self, x: torch.Tensor, h: int, w: int) -> torch.Tensor:
        c, heads, d = self.channels, self.num_heads, self.head_dim
        length = h * w
        reduced = self.cn1(x.reshape(-1, h, w, c).permute(0, 3, 1, 2))
        reduced = self.ln1(reduced.flatten(2).transpose(1, 2))  # (N, L', C)
        r = reduced.shape[1]
        q = self.query(x).reshape(-1, length, heads, d).transpose(1, 2)  # (N, heads, L, d)
        k = self.key(reduced).reshape(-1, r, heads, d).permute(0, 2, 3, 1)  # (N, heads, d, L')
        weights = torch.softmax(q @ k, dim=-1)  # (N, heads, L, L')
        v = self.value(reduced).reshape(-1, r, heads, c).transpose(1, 2).reshape(-1, heads * r, c)
        weights = weights.transpose(1, 2).reshape(-1, length, heads * r)  # heads side by side
        return weights @ v


class UnrolledLSTM(nn.LSTM):
    """An ``nn.LSTM`` (same parameters) whose forward is the eval-mode cell arithmetic as plain ops."""

    @classmethod
    def from_lstm(cls, lstm: nn.LSTM) -> UnrolledLSTM:
        if not lstm.batch_first or lstm.bidirectional or lstm.proj_size:
            raise ValueError("UnrolledLSTM supports batch-first, unidirectional LSTMs without projections")
        new = cls(lstm.input_size, lstm.hidden_size, lstm.num_layers, bias=lstm.bias, batch_first=True)
        new.load_state_dict(lstm.state_dict())
        return new.eval()

    def forward(self, x, hx=None):
        if hx is None:
            zeros = x.new_zeros(self.num_layers, x.shape[0], self.hidden_size)
            hx = (zeros, zeros)
        return lstm_inference(self, x, hx)


class StateSplitLSTM(UnrolledLSTM):
    """An ``UnrolledLSTM`` whose input is ``cat(image features, state)`` (the last ``STATE_DIM`` columns), with
    layer 0's input product split in two: ``features`` and ``state`` (5 columns, too small to quantise).

    The same function. Trained weights on the state columns (speed, attitude) are several times larger than
    on the image features, so one int8 scale per output channel over the whole row rounds the image weights
    coarsely; split, the image product gets its own scales and the state product stays float32.
    """

    @classmethod
    def from_lstm(cls, lstm: nn.LSTM) -> StateSplitLSTM:
        new = super().from_lstm(lstm)
        with torch.no_grad():
            w_ih = lstm.weight_ih_l0
            split = w_ih.shape[1] - STATE_DIM
            new.features = nn.Linear(split, w_ih.shape[0], bias=lstm.bias)
            new.features.weight.copy_(w_ih[:, :split])
            if lstm.bias:
                new.features.bias.copy_(lstm.bias_ih_l0 + lstm.bias_hh_l0)
            new.state = nn.Linear(STATE_DIM, w_ih.shape[0], bias=False)
            new.state.weight.copy_(w_ih[:, split:])
        return new.eval()

    def forward(self, x, hx=None):
        if hx is None:
            zeros = x.new_zeros(self.num_layers, x.shape[0], self.hidden_size)
            hx = (zeros, zeros)
        split = x.shape[-1] - STATE_DIM
        gates = self.features(x[..., :split]) + self.state(x[..., split:])
        return lstm_inference(self, None, hx, first_input_gates=gates)


class FoldedViTHead(nn.Module):
    """``leaky_relu(nn_fc1(cat(decoder(f), state)))`` with decoder and nn_fc1 multiplied out."""

    def __init__(self, decoder: nn.Linear, fc1: nn.Linear) -> None:
        super().__init__()
        with torch.no_grad():
            split = decoder.out_features
            w_features, w_state = fc1.weight[:, :split], fc1.weight[:, split:]
            self.features = nn.Linear(decoder.in_features, fc1.out_features)
            self.features.weight.copy_(w_features @ decoder.weight)
            self.features.bias.copy_(w_features @ decoder.bias + fc1.bias)
            self.state = nn.Linear(STATE_DIM, fc1.out_features, bias=False)
            self.state.weight.copy_(w_state)

    def forward(self, fused: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        return F.leaky_relu(self.features(fused) + self.state(state))


class _FoldedViT(nn.Module):
    """A ViT whose encode/head use ``FoldedViTHead`` (shares the encoder modules of ``vit``)."""

    def __init__(self, vit: ViT) -> None:
        super().__init__()
        self.vit = vit
        self.folded = FoldedViTHead(vit.decoder, vit.nn_fc1)
        self.is_recurrent = False
        self.use_state = vit.use_state
        self.model_name = vit.model_name

    def initial_hidden(self, batch_size: int, device=None, dtype=None):
        return None

    def forward(self, depth, desired_speed, quat, hidden=None):
        from vitfly.zoo.base import IMAGE_HEIGHT, IMAGE_WIDTH, check_inputs
        from vitfly.zoo.layers import state_vector

        b, t = check_inputs(depth, desired_speed, quat)
        fused = self.vit.fused_features(depth.reshape(b * t, 1, IMAGE_HEIGHT, IMAGE_WIDTH)).reshape(b, t, -1)
        x = self.folded(fused, state_vector(desired_speed, quat, self.use_state))
        return self.vit.nn_fc2(x), None


class _FoldedViTLSTM(nn.Module):
    """A ViT+LSTM whose decoder is multiplied into the LSTM's layer-0 input weights (shares ``net``'s modules)."""

    is_recurrent = True

    def __init__(self, net: ViTLSTM) -> None:
        super().__init__()
        self.net = net
        self.use_state = net.use_state
        self.model_name = net.model_name
        lstm, decoder = net.lstm, net.decoder
        with torch.no_grad():
            split = decoder.out_features
            w_ih = lstm.weight_ih_l0
            w_features, w_state = w_ih[:, :split], w_ih[:, split:]
            self.gates_features = nn.Linear(decoder.in_features, w_ih.shape[0])
            self.gates_features.weight.copy_(w_features @ decoder.weight)
            self.gates_features.bias.copy_(w_features @ decoder.bias + lstm.bias_ih_l0 + lstm.bias_hh_l0)
            self.gates_state = nn.Linear(STATE_DIM, w_ih.shape[0], bias=False)
            self.gates_state.weight.copy_(w_state)

    def initial_hidden(self, batch_size: int, device=None, dtype=None):
        return self.net.initial_hidden(batch_size, device, dtype)

    def forward(self, depth, desired_speed, quat, hidden=None):
        from vitfly.zoo.base import IMAGE_HEIGHT, IMAGE_WIDTH, check_inputs
        from vitfly.zoo.layers import state_vector

        b, t = check_inputs(depth, desired_speed, quat)
        fused = self.net.fused_features(depth.reshape(b * t, 1, IMAGE_HEIGHT, IMAGE_WIDTH)).reshape(b, t, -1)
        gates = self.gates_features(fused) + self.gates_state(state_vector(desired_speed, quat, self.use_state))
        if hidden is None:
            hidden = self.net.initial_hidden(b, depth.device, depth.dtype)
        out, hidden = lstm_inference(self.net.lstm, None, hidden, first_input_gates=gates)
        return self.net.nn_fc2(out), hidden


class _FoldedConvNet(nn.Module):
    """The ConvNet with batch norm, min-pool negations, average pool and state scale folded into its layers.

    With every batch-norm scale a > 0 (checked by ``foldable``), per channel
    ``min_pool(a * relu(z) + b) = a * relu(-max_pool(-z)) + b = -a * max_pool(min(-z, 0)) + b`` (relu and
    pooling are monotone), so conv1 is negated, clipped at 0 and max-pooled, and ``-a``, ``b`` go into
    conv2 (no padding: exact). The average pool (linear) is folded into fc0's image columns, and the 0.1
    speed scale into fc0's speed column. The head runs on (B*T, F) rows: one product per layer, no reshapes.
    """

    is_recurrent = False

    def __init__(self, net: ConvNet) -> None:
        super().__init__()
        self.use_state, self.model_name = net.use_state, net.model_name
        bn = net.bn1
        with torch.no_grad():
            a = bn.weight / torch.sqrt(bn.running_var + bn.eps)
            b = bn.bias - bn.running_mean * a
            self.conv1 = nn.Conv2d(1, 4, kernel_size=3, stride=3)
            self.conv1.weight.copy_(-net.conv1.weight)
            self.conv1.bias.copy_(-net.conv1.bias)
            self.conv2 = nn.Conv2d(4, 10, kernel_size=3, stride=2)
            self.conv2.weight.copy_(-net.conv2.weight * a[None, :, None, None])
            self.conv2.bias.copy_(net.conv2.bias + (net.conv2.weight * b[None, :, None, None]).sum(dim=(1, 2, 3)))
            # fc0 over the un-pooled conv2 output (10, 9, 14): each pooled input spreads 1/9 over its 3x3 window
            split = net.feature_dim
            w_pooled = net.fc0.weight[:, :split].reshape(-1, 1, 10, 7, 12)
            w_full = F.conv_transpose2d(w_pooled.reshape(-1, 1, 7, 12), torch.full((1, 1, 3, 3), 1.0 / 9.0))
            w_image = w_full.reshape(net.fc0.out_features, -1)
            # the state columns apart (float32 in the int8 path): their trained weights, and the raw speed,
            # are larger than the image's and would set the int8 scales (see StateSplitLSTM)
            self.fc0 = nn.Linear(w_image.shape[1], net.fc0.out_features, bias=False)
            self.fc0.weight.copy_(w_image)
            self.fc0_state = nn.Linear(STATE_DIM, net.fc0.out_features, bias=False)
            self.fc0_state.weight.copy_(net.fc0.weight[:, split:])
            self.fc0_state.weight[:, 0] *= SPEED_SCALE  # the state is [speed, quat] here, not [0.1 * speed, quat]
        self.fc1, self.fc2, self.fc3 = net.fc1, net.fc2, net.fc3

    @staticmethod
    def foldable(net: nn.Module) -> bool:
        bn = getattr(net, "bn1", None)
        return isinstance(net, ConvNet) and not bn.training and bool((bn.weight > 0).all())

    def initial_hidden(self, batch_size: int, device=None, dtype=None):
        return None

    def forward(self, depth, desired_speed, quat, hidden=None):
        from vitfly.zoo.base import IMAGE_HEIGHT, IMAGE_WIDTH, check_inputs

        b, t = check_inputs(depth, desired_speed, quat)
        z = torch.clamp(self.conv1(depth.reshape(b * t, 1, IMAGE_HEIGHT, IMAGE_WIDTH)), max=0.0)
        x = F.relu(self.conv2(F.max_pool2d(z, 2, 1)))
        x = self.fc0(x.flatten(1))
        if self.use_state:
            x = x + self.fc0_state(torch.cat((desired_speed.reshape(b * t, 1), quat.reshape(b * t, 4)), dim=-1))
        x = F.leaky_relu(x)
        x = torch.tanh(self.fc2(F.leaky_relu(self.fc1(x))))
        return self.fc3(x).reshape(b, t, 3), None


def _replace_modules(module: nn.Module, gelu: str) -> None:
    for name, child in module.named_children():
        if isinstance(child, SNLinear):
            setattr(module, name, plain_linear(child))
        elif isinstance(child, nn.LSTM):
            setattr(module, name, UnrolledLSTM.from_lstm(child))
        elif isinstance(child, MixFFN):
            setattr(module, name, ConvMixFFN(child, gelu))
        elif isinstance(child, EfficientSelfAttention):
            setattr(module, name, FoldedAttention(child))
        elif isinstance(child, nn.Conv2d) and not isinstance(child, nn.ConvTranspose2d):
            setattr(module, name, merge_conv_groups(child))
        else:
            _replace_modules(child, gelu)


def inference_copy(net: nn.Module, approximate_gelu: bool = False, fuse_ffn: bool = False) -> nn.Module:
    """An eval-mode copy of ``net`` with the rewrites above; same call contract and outputs.

    ``approximate_gelu`` runs the mix-FFN's GELU as its tanh approximation (|error| < 5e-4; about 6 % of the
    ViT's time at batch 1 on CPU): a different function, for the int8 fast path whose commands are checked
    against the exact network over recorded flights. ``fuse_ffn`` gives the ViTs' mix-FFNs as one dense
    convolution each (``FusedConvMixFFN``; the same function, for the int8 path's convolutions).
    """
    copy_ = copy.deepcopy(net).eval()
    if _FoldedConvNet.foldable(copy_):
        return _FoldedConvNet(copy_).eval()
    if fuse_ffn and isinstance(copy_, (ViT, ViTLSTM)):
        fuse_mix_ffns(copy_, "tanh" if approximate_gelu else "none", QUICK_GELU_STAGES.get(copy_.model_name, ()))
    _replace_modules(copy_, "tanh" if approximate_gelu else "none")
    if isinstance(copy_, (LSTMNet, UNetLSTM)):
        copy_.lstm = StateSplitLSTM.from_lstm(copy_.lstm)
    if isinstance(copy_, ViT):
        copy_ = _FoldedViT(copy_).eval()
    elif isinstance(copy_, ViTLSTM):
        copy_ = _FoldedViTLSTM(copy_).eval()
    return copy_
