"""int8 versions of exported policies for ONNX Runtime on CPUs with int8 dot-product units (AVX512-VNNI).

``quantize_int8(model_bytes)`` applies ONNX Runtime's *dynamic* quantisation to the large matrix products
only (``MatMul``, and ``Gemm`` rewritten as ``MatMul`` + ``Add``, whose weight has at least
``min_weight_elements`` entries): their weights are stored as int8 with one scale per output channel, and
each call quantises the product's input to uint8 from its own range and multiplies in integer arithmetic.
Convolutions, products of two activations, norms and activations stay float32. At batch 1 these products
are memory-bound (the ViT+LSTM's fused 4608 -> 512 input product alone is 9.4 MB of float32 weights, the
LSTMs' products several MB more), so int8 weights read a quarter of the bytes. Dynamic quantisation needs
no calibration data, so it cannot be mis-calibrated for a scene. ``FLOAT32_LARGEST`` lists architectures
whose largest products in int8 moved the commands beyond the tolerance over recorded flights; they stay float32.
The state inputs (speed, attitude) enter the products apart from the image features (``inference_copy``):
their trained weights are several times the image's and would set the int8 scales of whole rows.
On an x86 CPU without int8 dot-product instructions (VNNI; e.g. an AVX2-only AMD EPYC), ONNX Runtime multiplies
uint8 inputs by int8 weights in pairs summed in 16 bits, which saturate: there the weights are quantised to 7
bits (``reduce_range``; measured with the shipped LSTMnet, one 660 -> 1580 product moved the outputs by 0.87
with 8-bit weights, 0.10 with 7-bit ones), and ``FLOAT32_LARGEST_WITHOUT_VNNI`` adds the products that 7 bits
leave beyond the tolerance. The export records which (``vitfly.int8_reduce_range``).

Tried and dropped (measured with per-call CPU time, one thread): static (calibrated) int8, QDQ and
QOperator -- the ViT's grouped 3x3 convolutions and the LSTMs' products became slower than float32 (the LSTM
networks about 5x), and the ViT's 1x1 convolutions alone gained at most 8 % with output errors as large as
the dynamic products'; dynamic int8 convolutions (ConvInteger) -- slower than the float32 NCHWc kernels;
weight-only ``MatMulNBits`` (8 and 4 bit, block 32 / 128) -- no faster than dynamic int8 and no more
accurate; bf16 -- ONNX Runtime has no bf16 CPU kernels on x86, and eager PyTorch in bf16 (autocast or bf16
weights) is no faster than float32 eager at batch 1.

The ViTs' mix-FFNs (their largest cost: a 3x3 convolution with 8-channel groups, which float32 kernels
run at half efficiency) are a second, *static* int8 path, taken when the export is given calibration frames:
``inference_copy(fuse_ffn=True)`` multiplies each mix-FFN's first Linear into its grouped convolution
(``FusedConvMixFFN``, one dense 3x3 convolution, the same function), and ``_quantize_fused_convs`` runs it as
ONNX Runtime's channels-last ``QLinearConv``, whose symmetric int8 kernel uses the dot-product instructions:
about 90 us against about 300 us for the float pair per layer at batch 1. Its input and output ranges are
fixed by calibration (``calibrate_ranges`` over recorded expert flights, widened by ``RANGE_MARGIN``); a
frame far outside them saturates, which the command agreement over flights through other scenes checks.
Where the mix-FFN takes GELU's sigmoid approximation (``QUICK_GELU_STAGES``), the chain stays uint8 from the
convolution through the sigmoid (a table), the product and mlp2: the float GELU, its dequantisation and mlp2's
float product were a third of the ViT's int8 time.

The quantised graph computes a different function; ``vitfly.eval.agreement`` measures how far its
commands are from the float32 network's over recorded flights.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
from onnx import helper, numpy_helper

PRECISIONS = ("fp32", "int8")
VNNI_FLAGS = ("avx512_vnni", "avx_vnni", "amx_int8")  # /proc/cpuinfo flags of x86 int8 dot-product units
# architectures whose largest products stay float32 in the int8 path: (how many, from the largest down; why).
# Measured with the shipped trained weights (weights/) over recorded flights, benchmarks/fast_path_agreement.py
FLOAT32_LARGEST: dict[str, tuple[int, str]] = {
    "vit": (1, "its largest product (the decoder folded into the head, 4608 -> 256) in int8 moved the commands by "
            "up to 0.24 m/s (2.5 deg) over recorded flights (random weights), above the 0.15 m/s tolerance (8-bit "
            "block-wise weights, MatMulNBits, were no faster); its mix-FFN convolutions are int8 all the same"),
    "convnet": (2, "its trained output is near zero on some ticks (|v| 0.016), where normalising the command "
                "turns either product's int8 rounding (raw error about 1e-3) into up to 0.38 m/s; its float32 "
                "export is already within a quarter of the original's latency"),
}
# with 7-bit weights (an x86 CPU without VNNI), measured as FLOAT32_LARGEST with the shipped weights
FLOAT32_LARGEST_WITHOUT_VNNI: dict[str, tuple[int, str]] = {
    "lstmnet": (1, "on an AVX2-only CPU its largest product (image features into the first LSTM layer, 660 -> "
                "1580) with 7-bit weights moved the outputs by 0.10 over the export's four-tick check; in "
                "float32, the rest in int8: 0.016, against a tolerance of 0.05"),
    "vit_lstm": (1, "on an AVX2-only CPU its largest product (the decoder folded into the LSTM's first input "
                 "product, 4608 -> 512) with 7-bit weights moved the commands by up to 0.16 m/s over recorded "
                 "flights (random weights), above the 0.15 m/s tolerance"),
}


def int8_saturates() -> bool:
    """Whether this CPU multiplies ONNX Runtime's uint8 x int8 products through saturating 16-bit sums: an x86
    CPU whose flags name no VNNI unit (other architectures, and CPUs whose flags cannot be read, are taken as
    not saturating)."""
    import platform

    if platform.machine().lower() not in ("x86_64", "amd64", "i686", "x86"):
        return False
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    return "flags" in flags and not any(f" {flag}" in flags for flag in VNNI_FLAGS)


# smaller products gain nothing from int8 at batch 1: the per-call input quantisation costs more than it saves
MIN_WEIGHT_ELEMENTS = 16_384
PER_CHANNEL = True


def _large_products(model: onnx.ModelProto, min_weight_elements: int) -> list[str]:
    """Names of the MatMul nodes whose second input is an initializer with at least ``min_weight_elements``,
    smallest weight first."""
    sizes = {init.name: int(np.prod(init.dims)) for init in model.graph.initializer}
    large = [node for node in model.graph.node
             if node.op_type == "MatMul" and sizes.get(node.input[1], 0) >= min_weight_elements]  # fmt: skip
    return [node.name for node in sorted(large, key=lambda node: sizes[node.input[1]])]


def _gemms_as_matmuls(model: onnx.ModelProto, min_weight_elements: int) -> None:
    """Rewrite large ``Gemm(A, W, C)`` (constant W, alpha = beta = 1, no transA) as ``MatMul(A, W') + C`` in place.

    ONNX Runtime quantises MatMul dynamically but not Gemm (what a 2-D ``nn.Linear`` exports to).
    """
    inits = {init.name: init for init in model.graph.initializer}
    nodes = []
    for index, node in enumerate(model.graph.node):
        attrs = {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
        weight = inits.get(node.input[1]) if node.op_type == "Gemm" and len(node.input) > 1 else None
        plain = attrs.get("alpha", 1.0) == 1.0 and attrs.get("beta", 1.0) == 1.0 and not attrs.get("transA", 0)
        if weight is None or not plain or numpy_helper.to_array(weight).size < min_weight_elements:
            nodes.append(node)
            continue
        w = numpy_helper.to_array(weight)
        w = w.T.copy() if attrs.get("transB", 0) else w
        w_name = f"{node.input[1]}_matmul_{index}"
        model.graph.initializer.append(numpy_helper.from_array(w, w_name))
        name = node.name or f"gemm_{index}"
        has_bias = len(node.input) > 2 and node.input[2]
        product = f"{node.output[0]}_product" if has_bias else node.output[0]
        nodes.append(onnx.helper.make_node("MatMul", [node.input[0], w_name], [product], name=f"{name}_matmul"))
        if has_bias:
            nodes.append(onnx.helper.make_node("Add", [product, node.input[2]], [node.output[0]], name=f"{name}_bias"))
    del model.graph.node[:]
    model.graph.node.extend(nodes)


def quantize_int8(
    model_bytes: bytes,
    min_weight_elements: int = MIN_WEIGHT_ELEMENTS,
    calibration_depth: np.ndarray | None = None,
    reduce_range: bool | None = None,
) -> bytes:
    """The int8 version of an exported vitfly policy (its large products, less the largest for ``FLOAT32_LARGEST``);
    metadata kept, plus ``vitfly.precision = int8``, ``vitfly.int8_products`` (how many were quantised) and
    ``vitfly.int8_convolutions``. The fused mix-FFN convolutions (``FusedConvMixFFN``), when the export has
    them, need ``calibration_depth`` (N, 60, 90) frames in [0, 1] to fix their activation ranges.
    ``reduce_range``: 7-bit weights (None: where this CPU's int8 products saturate, ``int8_saturates``)."""
    from onnxruntime.quantization import QuantType, quantize_dynamic

    model = onnx.load_from_string(model_bytes)
    metadata = {p.key: p.value for p in model.metadata_props}
    chains = _ffn_chains(model)
    ranges = {}
    if chains:
        if calibration_depth is None:
            raise ValueError("this export has fused mix-FFN convolutions: give calibration_depth frames")
        ranges = calibrate_ranges(model_bytes, calibration_depth, [t for c in chains for t in c.tensors()])
    nodes = []
    _gemms_as_matmuls(model, min_weight_elements)
    nodes = _large_products(model, min_weight_elements)
    reduce_range = int8_saturates() if reduce_range is None else reduce_range
    keep = {**FLOAT32_LARGEST, **(FLOAT32_LARGEST_WITHOUT_VNNI if reduce_range else {})}
    keep_float32, _ = keep.get(metadata.get("vitfly.model", ""), (0, ""))
    nodes = nodes[: max(0, len(nodes) - keep_float32)]
    with tempfile.TemporaryDirectory(prefix="vitfly-int8-") as tmp:
        out = Path(tmp) / "int8.onnx"
        if nodes:
            quantize_dynamic(model, out, op_types_to_quantize=["MatMul", "Gemm"], nodes_to_quantize=nodes,
                             weight_type=QuantType.QInt8, per_channel=PER_CHANNEL,
                             reduce_range=reduce_range)
            model = onnx.load(out)
    if chains:
        _quantize_fused_convs(model, ranges)
    else:
        onnx.checker.check_model(model)  # (the checker knows no com.microsoft operators)
    metadata["vitfly.precision"] = "int8"
    metadata["vitfly.int8_products"] = str(len(nodes))
    metadata["vitfly.int8_convolutions"] = str(sum(1 if c.quick is None else 2 for c in chains))
    metadata["vitfly.int8_reduce_range"] = str(bool(reduce_range))
    del model.metadata_props[:]
    for key, value in metadata.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    return model.SerializeToString()


# the exported name of FusedConvMixFFN's convolution weight (vitfly.deploy.optimize)
FUSED_CONV_WEIGHT = "fused_conv.weight"
# calibrated activation ranges are widened by this factor (about zero) against frames unlike the calibration's
RANGE_MARGIN = 1.25


@dataclass
class _FfnChain:
    """One fused mix-FFN in the exported graph: ``before`` (Transpose NHWC -> NCHW) -> ``conv`` -> [``quick``:
    Mul(y, 1.702) -> Sigmoid -> Mul(y, s) -> ``mlp2`` (1x1 Conv)] -> ``after`` (Transpose NCHW -> NHWC)."""

    before: onnx.NodeProto
    conv: onnx.NodeProto
    after: onnx.NodeProto
    quick: tuple[onnx.NodeProto, onnx.NodeProto, onnx.NodeProto, onnx.NodeProto] | None = None

    def tensors(self) -> list[str]:
        """The tensors whose ranges calibration fixes."""
        if self.quick is None:
            return [self.conv.input[0], self.conv.output[0]]
        return [self.conv.input[0], self.conv.output[0], self.quick[2].output[0], self.quick[3].output[0]]


def _ffn_chains(model: onnx.ModelProto) -> list[_FfnChain]:
    """Every fused mix-FFN convolution (``FUSED_CONV_WEIGHT``) with the nodes around it."""
    producers = {out: node for node in model.graph.node for out in node.output}
    consumers: dict[str, list[onnx.NodeProto]] = {}
    for node in model.graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)

    def only(name: str, op_type: str, where: onnx.NodeProto) -> onnx.NodeProto:
        found = consumers.get(name, [])
        if len(found) != 1 or found[0].op_type != op_type:
            raise ValueError(f"{where.name}: unexpected graph around a fused mix-FFN convolution")
        return found[0]

    chains = []
    for conv in model.graph.node:
        if conv.op_type != "Conv" or not conv.input[1].endswith(FUSED_CONV_WEIGHT):
            continue
        before = producers.get(conv.input[0])
        perm = [list(a.ints) for a in before.attribute if a.name == "perm"] if before is not None else []
        if before is None or before.op_type != "Transpose" or perm != [[0, 3, 1, 2]]:
            raise ValueError(f"{conv.name}: expected a channels-last token grid transposed into the convolution")
        only(conv.input[0], "Conv", conv)
        after_conv = consumers.get(conv.output[0], [])
        if len(after_conv) == 1:
            chains.append(_FfnChain(before, conv, only(conv.output[0], "Transpose", conv)))
            continue
        scale = next((n for n in after_conv if n.op_type == "Mul" and n.input[1] in _constants(model)), None)
        if scale is None or len(after_conv) != 2:
            raise ValueError(f"{conv.name}: unexpected graph around a fused mix-FFN convolution")
        sigmoid = only(scale.output[0], "Sigmoid", conv)
        product = only(sigmoid.output[0], "Mul", conv)
        mlp2 = only(product.output[0], "Conv", conv)
        chains.append(_FfnChain(before, conv, only(mlp2.output[0], "Transpose", conv), (scale, sigmoid, product, mlp2)))
    return chains


def _constants(model: onnx.ModelProto) -> dict[str, np.ndarray]:
    values = {init.name: numpy_helper.to_array(init) for init in model.graph.initializer}
    for node in model.graph.node:
        if node.op_type == "Constant":
            values[node.output[0]] = numpy_helper.to_array(node.attribute[0].t)
    return values


def calibrate_ranges(model_bytes: bytes, depth: np.ndarray, tensors: list[str]) -> dict[str, tuple[float, float]]:
    """(min, max) of each of ``tensors`` over the frames ``depth`` (N, 60, 90), run one by one through the float
    model at 5 m/s, level attitude, zero recurrent state (the encoder, where these tensors are, sees only depth)."""
    import onnxruntime as ort

    model = onnx.load_from_string(model_bytes)
    del model.graph.output[:]
    for name in tensors:
        model.graph.output.append(helper.make_empty_tensor_value_info(name))
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.log_severity_level = 3
    session = ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
    depth = np.asarray(depth, dtype=np.float32)
    if depth.ndim != 3 or len(depth) == 0:
        raise ValueError(f"calibration depth: expected frames (N, 60, 90), got shape {depth.shape}")
    feed = {"desired_speed": np.full((1, 1, 1), 5.0, np.float32), "quat": np.zeros((1, 1, 4), np.float32)}
    feed["quat"][..., 0] = 1.0
    for arg in session.get_inputs():
        if arg.name in ("h0", "c0"):
            feed[arg.name] = np.zeros([1 if isinstance(d, str) else d for d in arg.shape], np.float32)
    low = dict.fromkeys(tensors, 0.0)
    high = dict.fromkeys(tensors, 0.0)
    for frame in depth:
        feed["depth"] = frame.reshape(1, 1, 1, *frame.shape)
        for name, value in zip(tensors, session.run(tensors, feed), strict=True):
            low[name], high[name] = min(low[name], float(value.min())), max(high[name], float(value.max()))
    return {name: (low[name], high[name]) for name in tensors}


def _uint8_params(low: float, high: float, margin: float = RANGE_MARGIN) -> tuple[np.float32, np.uint8]:
    """Scale and zero point of an asymmetric uint8 quantisation of [low, high] (always holding 0), widened."""
    low, high = min(low, 0.0) * margin, max(high, 0.0) * margin
    scale = max(high - low, 1e-8) / 255.0
    return np.float32(scale), np.uint8(np.clip(round(-low / scale), 0, 255))


def _int8_conv(prefix: str, x: str, x_scale: str, x_zero: str, x_scale_value: float, conv: onnx.NodeProto,
               inits: dict, y_scale: str, y_zero: str, out: str) -> tuple[list[onnx.NodeProto], dict[str, np.ndarray]]:
    """A channels-last ``QLinearConv`` computing float ``conv`` on uint8 ``x``: int8 weights, symmetric, one
    scale per output channel (the kernel ONNX Runtime runs with int8 dot-product instructions), int32 bias."""
    attrs = {a.name: helper.get_attribute_value(a) for a in conv.attribute}
    weight = numpy_helper.to_array(inits[conv.input[1]]).astype(np.float64)
    bias = numpy_helper.to_array(inits[conv.input[2]]).astype(np.float64)
    w_scale = np.maximum(np.abs(weight).reshape(len(weight), -1).max(axis=1), 1e-12) / 127.0
    constants = {
        f"{prefix}_w": np.clip(np.round(weight / w_scale[:, None, None, None]), -127, 127).astype(np.int8),
        f"{prefix}_w_scale": w_scale.astype(np.float32), f"{prefix}_w_zero": np.zeros(len(weight), np.int8),
        f"{prefix}_b": np.round(bias / (float(x_scale_value) * w_scale)).astype(np.int32),
    }  # fmt: skip
    conv_attrs = {k: attrs[k] for k in ("kernel_shape", "pads", "strides", "dilations") if k in attrs}
    w = f"{prefix}_w"
    inputs = [x, x_scale, x_zero, w, f"{w}_scale", f"{w}_zero", y_scale, y_zero, f"{prefix}_b"]
    node = helper.make_node("QLinearConv", inputs, [out], name=f"{prefix}_conv", domain="com.microsoft",
                            channels_last=1, **conv_attrs)  # fmt: skip
    return [node], constants


def _quantize_fused_convs(model: onnx.ModelProto, ranges: dict[str, tuple[float, float]]) -> None:
    """Each fused mix-FFN as ONNX Runtime's channels-last uint8 operators, in place.

    ``Transpose -> Conv -> Transpose`` becomes ``QuantizeLinear`` (the calibrated input range) -> ``QLinearConv``
    -> ``DequantizeLinear`` (the calibrated output range), reading and writing the channels-last tokens
    directly. A chain with the sigmoid GELU (``FusedConvMixFFN`` "quick") stays uint8 through it:
    ``QLinearSigmoid`` (a 256-entry table; the 1.702 goes into its input scale) -> ``QLinearMul`` ->
    ``QLinearConv`` (mlp2) -> ``DequantizeLinear``. Accumulation is exact int32; the error is the rounding of
    the activations (8 bits over their calibrated ranges) and of the weights.
    """
    inits = {init.name: init for init in model.graph.initializer}
    constants_all = _constants(model)
    drop, replace = set(), {}

    def scalar(name: str, value) -> str:
        model.graph.initializer.append(numpy_helper.from_array(np.asarray(value), name))
        return name

    for index, chain in enumerate(_ffn_chains(model)):
        p = f"vitfly_int8_ffn_{index}"
        x_name, y_name = chain.conv.input[0], chain.conv.output[0]
        xs_value, xz_value = _uint8_params(*ranges[x_name])
        xs, xz = scalar(f"{p}_x_scale", xs_value), scalar(f"{p}_x_zero", xz_value)
        ys_value, yz_value = _uint8_params(*ranges[y_name])
        ys, yz = scalar(f"{p}_y_scale", ys_value), scalar(f"{p}_y_zero", yz_value)
        nodes = [helper.make_node("QuantizeLinear", [chain.before.input[0], xs, xz], [f"{p}_xq"], name=f"{p}_quantize")]
        conv_nodes, constants = _int8_conv(p, f"{p}_xq", xs, xz, xs_value, chain.conv, inits, ys, yz, f"{p}_yq")
        nodes += conv_nodes
        if chain.quick is None:
            nodes.append(helper.make_node("DequantizeLinear", [f"{p}_yq", ys, yz], [chain.after.output[0]],
                                          name=f"{p}_dequantize"))  # fmt: skip
        else:
            scale_node, sigmoid, product, mlp2 = chain.quick
            factor = float(np.asarray(constants_all[scale_node.input[1]]).reshape(-1)[0])
            ss, sz = scalar(f"{p}_s_scale", np.float32(1.0 / 255.0)), scalar(f"{p}_s_zero", np.uint8(0))
            sig_in = scalar(f"{p}_sig_in_scale", np.float32(ys_value * factor))
            gs_value, gz_value = _uint8_params(*ranges[product.output[0]])
            gs, gz = scalar(f"{p}_g_scale", gs_value), scalar(f"{p}_g_zero", gz_value)
            os_value, oz_value = _uint8_params(*ranges[mlp2.output[0]])
            os_, oz = scalar(f"{p}_o_scale", os_value), scalar(f"{p}_o_zero", oz_value)
            nodes += [
                helper.make_node("QLinearSigmoid", [f"{p}_yq", sig_in, yz, ss, sz], [f"{p}_sq"], name=f"{p}_sigmoid",
                                 domain="com.microsoft"),
                helper.make_node("QLinearMul", [f"{p}_yq", ys, yz, f"{p}_sq", ss, sz, gs, gz], [f"{p}_gq"],
                                 name=f"{p}_gelu", domain="com.microsoft"),
            ]  # fmt: skip
            mlp2_nodes, mlp2_constants = _int8_conv(f"{p}_mlp2", f"{p}_gq", gs, gz, gs_value, mlp2, inits, os_, oz,
                                                     f"{p}_oq")
            nodes += mlp2_nodes
            constants.update(mlp2_constants)
            nodes.append(helper.make_node("DequantizeLinear", [f"{p}_oq", os_, oz], [chain.after.output[0]],
                                          name=f"{p}_dequantize"))  # fmt: skip
            drop.update(n.output[0] for n in chain.quick)
        model.graph.initializer.extend(numpy_helper.from_array(np.asarray(v), k) for k, v in constants.items())
        replace[chain.conv.output[0]] = nodes  # (nodes are known by their first output: outputs are unique)
        drop.update({chain.before.output[0], chain.after.output[0]})
    nodes = []
    for node in model.graph.node:
        if node.output[0] in replace:
            nodes.extend(replace[node.output[0]])
        elif node.output[0] not in drop:
            nodes.append(node)
    del model.graph.node[:]
    model.graph.node.extend(nodes)
    used = {name for node in model.graph.node for name in node.input}
    kept = [init for init in model.graph.initializer if init.name in used]
    del model.graph.initializer[:]
    model.graph.initializer.extend(kept)
    if not any(op.domain == "com.microsoft" for op in model.opset_import):
        model.opset_import.append(helper.make_opsetid("com.microsoft", 1))
