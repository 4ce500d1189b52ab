"""PolicyModule: the LightningModule that trains any registered network by behaviour cloning.

The network stays a plain ``nn.Module`` (``self.net``, built by ``create_model``); this module owns
the loss (paper eq. 1: MSE between the prediction and ``velocity_cmd / desired_speed`` averaged over
valid steps), Adam with the paper's linear warm-up (set per step), truncated BPTT by manual optimisation, and the
validation metrics (MSE, command cosine, and per-axis R^2 of the lateral and vertical commands, which
tell a learned command from a constant one). With ``static_shapes`` a step keeps the padded batch's shape
from end to end (for CUDA graphs, ``compile="reduce-overhead"``) and computes the same loss and gradients.
``create_policy(name, **kwargs)`` builds one; in LightningCLI YAML a registered name works as the model's
class (``model: vit_lstm``), because every registered name has a ``PolicyModule`` subclass of that name in
this module, created on first use.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from typing import Any

import lightning as L
import torch
import torch.nn.functional as F
from lightning.pytorch.utilities import rank_zero_warn
from torch import nn
from torchmetrics import MeanSquaredError, Metric, R2Score

from vitfly.errors import VitflyError
from vitfly.zoo.base import DepthPolicyNet
from vitfly.zoo.checkpoint import SENSOR_KEY, check_sensor, read_sensor, sensor_conflicts, vitfly_stamp
from vitfly.zoo.compiled import compile_encoder
from vitfly.zoo.layers import state_vector
from vitfly.zoo.masked_norm import FrameWeights, mask_batch_norm
from vitfly.zoo.registry import create_model, list_models
from vitfly.zoo.thread_tuner import ThreadTuner

CHUNK_KEYS = ("depth", "desired_speed", "quat", "velocity_cmd", "mask")
# per-axis R^2 of the normalised command, logged as <prefix>/r2_<name>: the axes that carry the avoidance
# (a constant command scores about 0 here, however well it does on MSE and cosine)
R2_AXES = {"lateral": 1, "vertical": 2}  # world y (left), world z (up)
MIN_SPEED_MPS = 1e-3  # guards the label division; real trajectories fly at >= 1 m/s
FUSED_ADAM_DEVICES = ("cpu", "cuda")
CHANNELS_LAST = (False, True, "cpu")  # model.channels_last: never, always, when training on a CPU
# model.compile: off, torch.compile's default mode, or CUDA graphs (static shapes only)
COMPILE_MODES = {False: None, True: "default", "default": "default", "reduce-overhead": "reduce-overhead"}


def fusable(params) -> bool:
    """Whether torch's fused Adam may update ``params``: each on a device it has a kernel for, and contiguous.
    On the CPU (torch 2.15) a parameter in another layout (channels-last) whose moments are contiguous, as every
    resume from vitfly's checkpoints makes them, gets wrong updates (tests/test_fast_paths.py); the foreach and
    for-loop kernels are exact there."""
    return all(p.device.type in FUSED_ADAM_DEVICES and p.is_contiguous() for p in params)


def wants_channels_last(setting: bool | str, device: torch.device | str) -> bool:
    """Whether ``model.channels_last`` (``CHANNELS_LAST``) puts the network in channels-last layout on ``device``."""
    return setting is True or (setting == "cpu" and torch.device(device).type == "cpu")


def normalised_target(velocity_cmd: torch.Tensor, desired_speed: torch.Tensor) -> torch.Tensor:
    """The label of paper eq. 1: world-frame command (m/s) divided by the desired speed (m/s)."""
    return velocity_cmd / desired_speed.clamp_min(MIN_SPEED_MPS)


def masked_mse(prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean squared error over the valid steps only (padding is indexed away, never multiplied by 0)."""
    return F.mse_loss(prediction[mask], target[mask])


def avoidance_weights(target: torch.Tensor, avoid_weight: float) -> torch.Tensor:
    """Per-step loss weights ``1 + avoid_weight * |(y, z) of the normalised label|``, shape (N,).

    Most labels are straight flight; weighting the steps by how hard the expert swerves makes the rare
    avoidance manoeuvres count for more of the gradient (``avoid_weight`` 0: every step 1, paper eq. 1).
    """
    return 1.0 + avoid_weight * target[..., 1:].norm(dim=-1)


def weighted_masked_mse(
    prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, avoid_weight: float
) -> torch.Tensor:
    """``masked_mse`` with each valid step weighted by ``avoidance_weights`` (a weighted mean over steps)."""
    if not avoid_weight:
        return masked_mse(prediction, target, mask)
    pred, tgt = prediction[mask], target[mask]
    weights = avoidance_weights(tgt, avoid_weight)
    per_step = (pred.float() - tgt.float()).pow(2).mean(dim=-1)
    return (weights * per_step).sum() / weights.sum()


def dense_masked_mse(
    prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, avoid_weight: float = 0.0
) -> torch.Tensor:
    """``weighted_masked_mse`` over the whole padded (B, T) tensor, padding weighted 0: the same value, but no
    shape depends on the mask and nothing waits for the device (boolean indexing syncs with it on CUDA)."""
    per_step = (prediction.float() - target.float()).pow(2).mean(dim=-1)
    weights = mask.to(per_step.dtype)
    if avoid_weight:
        weights = weights * avoidance_weights(target.float(), avoid_weight)
    # where, not a product: whatever the padding holds (even inf) it adds exactly 0
    return torch.where(mask, weights * per_step, 0.0).sum() / weights.sum()


def detach_hidden(hidden: Any) -> Any:
    """The recurrent state cut from the graph (tensors, or tuples/lists of them; None stays None)."""
    if hidden is None:
        return None
    if isinstance(hidden, torch.Tensor):
        return hidden.detach()
    return type(hidden)(detach_hidden(h) for h in hidden)


class CommandCosine(Metric):
    """Mean cosine similarity between predicted and expert command directions, kept as two sums.

    (torchmetrics' CosineSimilarity keeps every sample; this keeps O(1) state and syncs by summing.)
    """

    full_state_update = False
    higher_is_better = True

    def __init__(self, eps: float = 1e-8, **kwargs) -> None:
        super().__init__(**kwargs)
        self.eps = eps
        self.add_state("cos_sum", default=torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("count", default=torch.tensor(0, dtype=torch.long), dist_reduce_fx="sum")

    def update(self, prediction: torch.Tensor, target: torch.Tensor) -> None:
        """prediction, target: (N, 3) commands of N valid steps."""
        cos = F.cosine_similarity(prediction, target, dim=-1, eps=self.eps)
        self.cos_sum += cos.sum().to(torch.float64)
        self.count += cos.numel()

    def compute(self) -> torch.Tensor:
        return (self.cos_sum / self.count.clamp_min(1)).to(torch.float32)


def check_policy_arguments(
    avoid_weight: float = 0.0,
    tbptt_steps: int | None = None,
    compile: bool | str = False,
    static_shapes: bool = False,
    cpu_threads: int | str | None = "auto",
    channels_last: bool | str = False,
) -> str | None:
    """One error line naming the field for a bad PolicyModule argument (``vitfly fit`` checks its config with
    this before building anything); returns the torch.compile mode (None: no compilation)."""
    threads_ok = cpu_threads in (None, "auto") or (
        isinstance(cpu_threads, int) and not isinstance(cpu_threads, bool) and cpu_threads >= 1
    )
    if not threads_ok:
        raise VitflyError(f"model.cpu_threads: expected auto, a thread count >= 1 or null, got {cpu_threads!r}")
    if channels_last not in CHANNELS_LAST:
        raise VitflyError(f"model.channels_last: expected false, true or cpu, got {channels_last!r}")
    if avoid_weight < 0:
        raise VitflyError(f"model.avoid_weight: expected a weight >= 0, got {avoid_weight}")
    if tbptt_steps is not None and tbptt_steps < 1:
        raise VitflyError(f"model.tbptt_steps: expected a positive number of steps or null, got {tbptt_steps}")
    compile_mode = COMPILE_MODES.get(compile) if isinstance(compile, (bool, str)) else None
    if compile_mode is None and compile is not False:
        raise VitflyError(f"model.compile: expected false, true (default mode) or reduce-overhead, got {compile!r}")
    if compile_mode == "reduce-overhead" and not static_shapes:
        raise VitflyError("model.compile: reduce-overhead (CUDA graphs replay fixed shapes) needs "
                          "model.static_shapes: true, with data.time_bucket_steps set")
    return compile_mode


def lr_factor(epoch_progress: float, warmup_epochs: float, start: float, decay: float, max_epochs: float) -> float:
    """Learning-rate multiplier after ``epoch_progress`` epochs (fractional) of training (paper code).

    Linear warm-up from ``start`` to 1 over ``warmup_epochs``; then constant when ``decay`` is 1, else
    exponential decay reaching ``decay`` after a further ``max_epochs`` epochs (the paper code's optional
    decay uses 0.1).
    """
    if epoch_progress < warmup_epochs:
        return start + (1.0 - start) * epoch_progress / warmup_epochs
    if decay == 1.0 or max_epochs <= 0:
        return 1.0
    return decay ** ((epoch_progress - warmup_epochs) / max_epochs)


class PolicyModule(L.LightningModule):
    """Behaviour cloning of the expert's velocity command with truncated BPTT.

    Args:
        model: registry name of the network (None: the class's own network, e.g. ``vit_lstm``).
        use_state: feed desired speed and attitude to the network (False: zeros, paper ablation).
        model_kwargs: extra keyword arguments of the network's builder (plain values).
        lr: Adam learning rate after warm-up (paper: 1e-4).
        warmup_epochs: epochs of linear warm-up (paper: 5).
        warmup_start_factor: lr factor at the start of the warm-up (paper: 0.1).
        lr_decay: lr factor reached ``max_epochs`` epochs after warm-up, exponentially (1.0: constant, the
            paper's setting; 0.1: the paper code's optional decay). The factor is set before every
            optimiser step from the fractional epoch, so a resumed run continues the same schedule.
        weight_decay: Adam weight decay.
        avoid_weight: weight each step's loss by ``1 + avoid_weight * |lateral, vertical label|`` (normalised
            label), so avoidance manoeuvres outweigh straight flight (0: paper eq. 1, every step alike).
            Validation and test metrics stay unweighted.
        tbptt_steps: time steps per optimiser step; each batch is walked in chunks of this length with
            the recurrent state carried across chunks, detached (None: the whole batch at once).
        gradient_clip_val: clip the gradient norm to this value before each step (None: no clipping).
        compile: ``torch.compile`` the network's image encoder (``vitfly.zoo.compile_encoder``; one
            warning and eager execution where the platform has no compiler): ``true`` (or ``default``) in
            torch.compile's default mode; ``reduce-overhead`` records CUDA graphs of it on CUDA (eager on other
            devices), which needs ``static_shapes``. Weights and checkpoints are the same either way.
        static_shapes: keep each batch's padded shape through the training step: TBPTT chunks are not trimmed
            of trailing padding, every frame goes through the image encoder (batch norm takes its statistics
            from the real frames only, ``vitfly.zoo.masked_norm``) and the loss is a masked sum. Loss and
            gradients are those of the default path (to float rounding; LSTM dropout masks are drawn for the
            padded shape). With the datamodule's ``time_bucket_steps`` a step then has one of a few shapes,
            which is what CUDA graphs need.
        cpu_threads: intra-op threads for training on the CPU: ``auto`` measures steps with all threads
            and with one and keeps the faster, re-measuring every 100 steps (``vitfly.zoo.thread_tuner``:
            on a machine shared with other work one thread can be several times faster); a number fixes
            it; None leaves torch's setting alone.
        channels_last: train the network's 4-D weights (convolutions) in channels-last memory layout: ``true``,
            ``cpu`` (only when training on a CPU: the paper arm's UNet+LSTM step ran 1.99x faster so on a
            2-core AVX512 CPU, docs/performance.md) or ``false``. The same arithmetic in another order (weights
            within float rounding of the contiguous run's); Adam runs unfused for such weights (``fusable``),
            checkpoints hold the weights as ever.
    """

    default_model = "convnet"

    def __init__(
        self,
        model: str | None = None,
        use_state: bool = True,
        model_kwargs: dict | None = None,
        lr: float = 1e-4,
        warmup_epochs: float = 5,
        warmup_start_factor: float = 0.1,
        lr_decay: float = 1.0,
        weight_decay: float = 0.0,
        avoid_weight: float = 0.0,
        tbptt_steps: int | None = 32,
        gradient_clip_val: float | None = None,
        compile: bool | str = False,
        cpu_threads: int | str | None = "auto",
        static_shapes: bool = False,
        channels_last: bool | str = False,
    ) -> None:
        super().__init__()
        model = model or type(self).default_model  # resolved before save_hyperparameters records it
        model_kwargs = dict(model_kwargs or {})
        compile_mode = check_policy_arguments(avoid_weight, tbptt_steps, compile, static_shapes, cpu_threads,
                                              channels_last)
        self.save_hyperparameters()
        # LightningCLI records the arguments as given (model=None); checkpoints must name the network
        self.hparams["model"], self.hparams["model_kwargs"] = model, model_kwargs
        self.automatic_optimization = False
        self.net: nn.Module = create_model(model, use_state=use_state, **model_kwargs)
        self.static_shapes = static_shapes
        # frame weights read by the network's batch norms (None: it has none, or static_shapes is off)
        self._frame_weights: FrameWeights | None = mask_batch_norm(self.net) if static_shapes else None
        self.compile_mode = compile_mode
        if compile_mode == "default":
            compile_encoder(self.net)
        elif compile_mode is not None:
            compile_encoder(self.net, mode=compile_mode)
        self.tbptt_steps = tbptt_steps
        self.gradient_clip_val = gradient_clip_val
        self.cpu_threads = cpu_threads
        self.channels_last = channels_last
        self._thread_tuner: ThreadTuner | None = None
        self.val_mse = MeanSquaredError()
        self.val_cos = CommandCosine()
        self.test_mse = MeanSquaredError()
        self.test_cos = CommandCosine()
        self.val_r2 = nn.ModuleDict({axis: R2Score() for axis in R2_AXES})
        self.test_r2 = nn.ModuleDict({axis: R2Score() for axis in R2_AXES})

    @property
    def is_recurrent(self) -> bool:
        return bool(getattr(self.net, "is_recurrent", False))

    # -- forward ---------------------------------------------------------------------------------

    def forward(self, depth, desired_speed, quat, hidden=None):
        """The network's call contract: (B, T, ...) inputs -> (velocity / desired speed (B, T, 3), hidden)."""
        return self.net(depth, desired_speed, quat, hidden)

    def _forward_valid(self, depth, desired_speed, quat, hidden, mask, all_valid: bool | None = None):
        """Forward in which padded frames never enter the image encoder (nor its batch-norm statistics).

        Zoo networks (DepthPolicyNet with the stock forward) encode only the valid frames; padded
        steps get zero features, which only the masked-out outputs after them can see.
        """
        net = self.net
        if all_valid is None:
            all_valid = bool(mask.all())
        if all_valid or not isinstance(net, DepthPolicyNet) or type(net).forward is not DepthPolicyNet.forward:
            return net(depth, desired_speed, quat, hidden)
        b, t = mask.shape
        valid = net.encode(depth[mask])
        features = valid.new_zeros((b, t, valid.shape[-1]))
        features[mask] = valid
        return net.head(features, state_vector(desired_speed, quat, net.use_state), hidden)

    def _forward_all_frames(self, depth, desired_speed, quat, hidden, mask):
        """Forward over every frame of the padded batch (``static_shapes``): one shape per batch shape.

        Batch norms weigh the frames by ``mask`` (statistics from real frames only); padding sits at the end
        of each row and the LSTMs are causal, so the real steps' outputs are those of the unpadded batch.
        """
        weights = self._frame_weights
        if weights is not None and self.net.training:
            weights.weights = mask.reshape(-1).to(torch.float32)  # frame order of the network's (B * T) reshape
            if self.compile_mode is not None:
                torch._dynamo.maybe_mark_dynamic(weights.weights, 0)  # as the frames: one graph for all counts
        try:
            return self.net(depth, desired_speed, quat, hidden)
        finally:
            if weights is not None:
                weights.weights = None

    # -- training: truncated BPTT with manual optimisation -----------------------------------------

    def tbptt_chunks(self, batch: Mapping[str, torch.Tensor]) -> Iterator[dict[str, Any]]:
        """The batch cut along time into chunks of ``tbptt_steps`` (``.split(k, dim=1)``), each trimmed
        of trailing all-padding steps; stops at the first chunk without a valid step.

        Chunk bounds and valid-frame counts come from one host copy of the (B, T) mask, so the loop
        over chunks waits for the device once per batch, not several times per chunk; not at all when
        the batch carries its rows' lengths on the host (``lengths_host``, the datamodule's resident
        batches: trajectories are padded at the end, so the mask is ``step < length``). Each chunk also
        carries ``n_valid`` (its number of valid steps, a Python int) and ``all_valid``. With
        ``static_shapes`` chunks keep their full length (the last one reaching into the padding is not
        trimmed), so every chunk of a batch padded to a multiple of ``tbptt_steps`` has the same shape.
        """
        mask = batch["mask"]
        k = self.tbptt_steps or mask.shape[1]
        lengths = batch.get("lengths_host")
        if lengths is not None and lengths.device.type == "cpu" and lengths.shape == mask.shape[:1]:
            host_mask = torch.arange(mask.shape[1]).unsqueeze(0) < lengths.unsqueeze(1)  # no wait for the device
        else:
            host_mask = mask.cpu()
        valid_steps = host_mask.any(dim=0)
        if not bool(valid_steps.any()):
            return
        end = int(valid_steps.nonzero().max()) + 1  # trajectories are padded at the end: nothing valid follows
        if self.static_shapes:
            end = min(mask.shape[1], math.ceil(end / k) * k)
        for lo in range(0, end, k):
            steps = min(k, end - lo)
            piece = host_mask[:, lo : lo + steps]
            chunk = {key: batch[key][:, lo : lo + steps] for key in CHUNK_KEYS}
            chunk["n_valid"] = int(piece.sum())
            chunk["all_valid"] = chunk["n_valid"] == piece.numel()
            yield chunk

    def chunk_loss(self, chunk: Mapping[str, torch.Tensor], hidden: Any = None) -> tuple[torch.Tensor, Any]:
        """Paper eq. 1 on one chunk, starting from recurrent state ``hidden``: (loss, state after the chunk)."""
        mask, speed = chunk["mask"], chunk["desired_speed"]
        if self.static_shapes:
            if self.compile_mode == "reduce-overhead" and mask.is_cuda:
                # a new training step: the CUDA graphs may reuse the previous step's output memory
                torch.compiler.cudagraph_mark_step_begin()
            prediction, hidden = self._forward_all_frames(chunk["depth"], speed, chunk["quat"], hidden, mask)
            target = normalised_target(chunk["velocity_cmd"], speed)
            return dense_masked_mse(prediction, target, mask, self.hparams.avoid_weight), hidden
        all_valid = chunk.get("all_valid")
        prediction, hidden = self._forward_valid(chunk["depth"], speed, chunk["quat"], hidden, mask, all_valid)
        target = normalised_target(chunk["velocity_cmd"], speed)
        return weighted_masked_mse(prediction, target, mask, self.hparams.avoid_weight), hidden

    def rank_chunks(self, batch: Mapping[str, torch.Tensor]) -> Iterator[tuple[dict[str, torch.Tensor] | None, float]]:
        """(chunk, loss weight) per optimiser step: ``tbptt_chunks`` with weight 1 in a single process.

        Under data parallelism every backward all-reduces the gradients, so every rank must take as many
        optimiser steps as the rank with the most chunks (a rank that stopped early would leave the others
        waiting forever): a rank out of chunks yields ``(None, 0.0)``. Weights make the averaged gradient
        that of the mean over all ranks' valid steps of the chunk, as one process holding every rank's
        batch would compute it: ``world_size * n_rank / n_all``.
        """
        trainer = self.trainer
        world = trainer.world_size
        if world == 1:
            yield from ((chunk, 1.0) for chunk in self.tbptt_chunks(batch))
            return
        chunks = list(self.tbptt_chunks(batch))
        counts = [int(c["mask"].sum()) for c in chunks]  # valid steps per chunk, each >= 1
        reduce = trainer.strategy.reduce
        steps = int(reduce(torch.tensor(len(chunks), device=self.device), reduce_op="max"))
        padded = torch.tensor(counts + [0] * (steps - len(chunks)), dtype=torch.long, device=self.device)
        totals = reduce(padded, reduce_op="sum").tolist()
        for i, total in enumerate(totals):
            yield (chunks[i], world * counts[i] / total) if i < len(chunks) else (None, 0.0)

    def _zero_loss(self) -> torch.Tensor:
        """A loss with zero gradient for every trainable parameter: a rank without data for this step still
        joins the other ranks' gradient all-reduce."""
        return sum(p.sum() for p in self.parameters() if p.requires_grad) * 0.0

    def on_fit_start(self) -> None:
        datamodule = getattr(self.trainer, "datamodule", None)
        if self.static_shapes and datamodule is not None and getattr(datamodule, "time_bucket_steps", None) is None:
            rank_zero_warn("model.static_shapes without data.time_bucket_steps: every trajectory length is a shape "
                           "of its own (set data.time_bucket_steps to bound them)")
        if self.device.type != "cpu" or self.cpu_threads is None:
            return
        if self.cpu_threads == "auto":
            self._thread_tuner = ThreadTuner()
        else:
            torch.set_num_threads(self.cpu_threads)

    def setup(self, stage: str) -> None:
        # before the strategy builds the optimiser, which must see the layout (``fusable``)
        if wants_channels_last(self.channels_last, self.trainer.strategy.root_device):
            self.net.to(memory_format=torch.channels_last)

    def on_train_start(self) -> None:
        # a resumed optimiser takes its groups' settings from the checkpoint, ``fused`` among them: a network
        # saved contiguous and resumed in another layout would get the fused kernel back (see ``fusable``)
        for opt in self.trainer.optimizers:
            for group in opt.param_groups:
                if group.get("fused") and not fusable(group["params"]):
                    group["fused"] = None

    def on_fit_end(self) -> None:
        if self._thread_tuner is not None:
            self._thread_tuner.restore()
            self._thread_tuner = None

    def training_step(self, batch: Mapping[str, torch.Tensor], batch_idx: int) -> torch.Tensor:
        opt = self.optimizers()
        hidden = None
        loss_sum = torch.zeros((), device=batch["mask"].device)
        n_valid = 0
        tuner = self._thread_tuner
        max_steps = self.trainer.max_steps
        for chunk, weight in self.rank_chunks(batch):
            # max_steps counts optimiser steps, several per batch here: stop inside the batch to end on the dot
            if 0 <= max_steps <= self.trainer.global_step:
                break
            if tuner is not None:
                tuner.before_step()
            if chunk is None:  # DDP: this rank's batch has ended, another rank's has not
                loss = self._zero_loss()
            else:
                loss, hidden = self.chunk_loss(chunk, hidden)
            self._set_lr(opt, batch_idx)
            opt.zero_grad()
            self.manual_backward(loss if weight == 1.0 else loss * weight)
            if self.gradient_clip_val:
                self.clip_gradients(opt, gradient_clip_val=self.gradient_clip_val, gradient_clip_algorithm="norm")
            opt.step()
            if chunk is None:
                continue
            hidden = detach_hidden(hidden)  # carried into the next chunk, cut from this chunk's graph
            n = chunk["n_valid"]
            if tuner is not None:
                tuner.after_step(n)
            loss_sum += loss.detach() * n
            n_valid += n
        mean_loss = loss_sum / max(n_valid, 1)
        # sync_dist: under DDP the mean over every rank's valid steps (a no-op in a single process)
        n = max(n_valid, 1)
        self.log("train/loss", mean_loss, on_step=True, on_epoch=True, prog_bar=True, batch_size=n, sync_dist=True)
        self.log("lr", opt.param_groups[0]["lr"], on_step=False, on_epoch=True, sync_dist=True)
        return mean_loss

    def _set_lr(self, opt, batch_idx: int) -> None:
        hp = self.hparams
        trainer = self.trainer
        batches = trainer.num_training_batches if trainer.num_training_batches not in (0, float("inf")) else 1
        progress = self.current_epoch + batch_idx / batches
        max_epochs = trainer.max_epochs if trainer.max_epochs and trainer.max_epochs > 0 else 0
        factor = lr_factor(progress, hp.warmup_epochs, hp.warmup_start_factor, hp.lr_decay, max_epochs)
        for group in opt.param_groups:
            group["lr"] = hp.lr * factor

    # -- checkpoints: the training sensor travels with the weights --------------------------------

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Store the sensor of the training dataset (``datamodule.sensor``: depth range, camera, control rate) as
        the checkpoint's top-level ``sensor``; without one, keep the sensor of the checkpoint this run started
        from. ``vitfly`` says which vitfly wrote it (``vitfly.zoo.checkpoint.vitfly_stamp``)."""
        checkpoint["vitfly"] = vitfly_stamp()
        datamodule = getattr(self._trainer, "datamodule", None) if self._trainer is not None else None
        sensor = getattr(datamodule, "sensor", None) or getattr(self, "_loaded_sensor", None)
        if sensor:
            checkpoint[SENSOR_KEY] = check_sensor(sensor, "training dataset")

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Keep the checkpoint's sensor; a resumed fit on data from another sensor is refused (one line)."""
        source = "checkpoint"
        trainer = self._trainer
        if trainer is not None and trainer.ckpt_path:
            source = str(trainer.ckpt_path)
        self._loaded_sensor = read_sensor(checkpoint, source)
        if trainer is None or trainer.state.fn != "fit":
            return
        current = getattr(trainer.datamodule, "sensor", None)
        conflicts = sensor_conflicts(self._loaded_sensor, current)
        if conflicts:
            raise VitflyError(
                f"{source}: trained on data from another sensor than {getattr(trainer.datamodule, 'data_path', '')} "
                f"({'; '.join(conflicts)}); train a new run on it instead of resuming"
            )

    def configure_optimizers(self):
        hp = self.hparams
        params = list(self.net.parameters())
        # one fused kernel for all parameters instead of ~10 small ops per parameter tensor (the profiled
        # CPU step spent ~5 % in Adam's per-tensor ops); same update rule. Not with gradient clipping:
        # Lightning's mixed-precision plugin refuses to clip for an optimiser that unscales internally
        fused = (not hp.gradient_clip_val and fusable(params)) or None
        return torch.optim.Adam(params, lr=hp.lr * hp.warmup_start_factor, weight_decay=hp.weight_decay, fused=fused)

    # -- validation / test / predict ------------------------------------------------------------

    def on_validation_epoch_start(self) -> None:
        """DDP: average the ranks' batch-norm running statistics before validating.

        Each rank updates them from its own batches, and Lightning's DDP with manual optimisation never
        broadcasts buffers after the first forward; averaged, every rank validates the same network, the
        one rank 0 then checkpoints.
        """
        if self.trainer.world_size == 1:
            return
        reduce = self.trainer.strategy.reduce
        for module in self.modules():
            if isinstance(module, nn.modules.batchnorm._BatchNorm) and module.running_mean is not None:
                module.running_mean.copy_(reduce(module.running_mean.clone(), reduce_op="mean"))
                module.running_var.copy_(reduce(module.running_var.clone(), reduce_op="mean"))

    def _evaluate(self, batch, mse: MeanSquaredError, cos: CommandCosine, r2: nn.ModuleDict, prefix: str) -> None:
        prediction, _ = self(batch["depth"], batch["desired_speed"], batch["quat"])
        mask = batch["mask"]
        pred = prediction[mask]
        target = normalised_target(batch["velocity_cmd"], batch["desired_speed"])[mask]
        mse.update(pred, target)
        cos.update(pred, target)
        n = int(mask.sum())
        self.log(f"{prefix}/loss", mse, on_step=False, on_epoch=True, prog_bar=True, batch_size=n)
        self.log(f"{prefix}/cosine", cos, on_step=False, on_epoch=True, batch_size=n)
        for name, axis in R2_AXES.items():
            r2[name].update(pred[:, axis], target[:, axis])
            self.log(f"{prefix}/r2_{name}", r2[name], on_step=False, on_epoch=True, batch_size=n)

    def validation_step(self, batch, batch_idx: int) -> None:
        self._evaluate(batch, self.val_mse, self.val_cos, self.val_r2, "val")

    def test_step(self, batch, batch_idx: int) -> None:
        self._evaluate(batch, self.test_mse, self.test_cos, self.test_r2, "test")

    def predict_step(self, batch, batch_idx: int, dataloader_idx: int = 0) -> dict[str, torch.Tensor]:
        """Per step: ``velocity`` (network output, command / desired speed), ``velocity_mps`` (times the
        desired speed, world frame), plus ``mask``, ``traj_index`` and ``start`` to trace each row back."""
        prediction, _ = self(batch["depth"], batch["desired_speed"], batch["quat"])
        out = {
            "velocity": prediction,
            "velocity_mps": prediction * batch["desired_speed"],
            "mask": batch["mask"],
            "traj_index": batch["traj_index"],
        }
        if "start" in batch:
            out["start"] = batch["start"]
        return out


_POLICY_CLASSES: dict[str, type[PolicyModule]] = {}


def policy_class(name: str) -> type[PolicyModule]:
    """The PolicyModule subclass named after registered network ``name`` (its default ``model``)."""
    if name not in list_models():
        raise VitflyError(f"unknown model {name!r}; known models: {', '.join(list_models())}")
    cls = _POLICY_CLASSES.get(name)
    if cls is None:
        cls = type(
            name,
            (PolicyModule,),
            {"__module__": __name__, "default_model": name, "__doc__": f"PolicyModule training the {name!r} network."},
        )
        _POLICY_CLASSES[name] = cls
    return cls


def register_policy_classes() -> list[str]:
    """Create the per-name subclasses for every registered network (so ``model: NAME`` resolves)."""
    names = list_models()
    for name in names:
        policy_class(name)
    return names


def create_policy(name: str, **kwargs) -> PolicyModule:
    """The LightningModule that trains registered network ``name`` (kwargs: PolicyModule's arguments)."""
    return policy_class(name)(**kwargs)


def __getattr__(attr: str):
    # ``vitfly.zoo.policy.vit_lstm`` imports by path (config files and checkpoints name it that way)
    if attr in list_models():
        return policy_class(attr)
    raise AttributeError(f"module {__name__!r} has no attribute {attr!r}")
