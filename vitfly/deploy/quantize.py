"""int8 versions of exported policies for ONNX Runtime on CPUs with int8 dot-product units (AVX512-VNNI).

``quantize_int8(model_bytes)`` applies ONNX Runtime's *dynamic* quantisation to the large matrix products
only (``MatMul``, and ``Gemm`` rewritten as ``MatMul`` + ``Add``, whose weight has at least
``min_weight_elements`` entries): their weights are stored as int8 with one scale per output channel, and
each call quantises the product's input to uint8 from its own range and multiplies in integer arithmetic.
Convolutions, products of two activations, norms and activations stay float32. At batch 1 these products
are memory-bound (the ViT+LSTM's fused 4608 -> 512 input product alone is 9.4 MB of float32 weights, the
LSTMs' products several MB more), so int8 weights read a quarter of the bytes. Dynamic quantisation needs
no calibration data, so it cannot be mis-calibrated for a scene. ``FLOAT32_MODELS`` lists architectures
whose int8 commands strayed beyond the tolerance over recorded flights; they keep float32 products.

Tried and dropped (measured with per-call CPU time, one thread): static (calibrated) int8, QDQ and
QOperator -- the ViT's grouped 3x3 convolutions and the LSTMs' products became slower than float32 (the LSTM
networks about 5x), and the ViT's 1x1 convolutions alone gained at most 8 % with output errors as large as
the dynamic products'; dynamic int8 convolutions (ConvInteger) -- slower than the float32 NCHWc kernels;
weight-only ``MatMulNBits`` (8 and 4 bit, block 32 / 128) -- no faster than dynamic int8 and no more
accurate; bf16 -- ONNX Runtime has no bf16 CPU kernels on x86, and eager PyTorch in bf16 (autocast or bf16
weights) is no faster than float32 eager at batch 1.

The quantised graph computes a different function; ``vitfly.eval.agreement`` measures how far its
commands are from the float32 network's over recorded flights.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import onnx
from onnx import numpy_helper

PRECISIONS = ("fp32", "int8")
# architectures whose products stay float32 in the int8 path, and why (benchmarks/fast_path_agreement.py)
FLOAT32_MODELS = {
    "vit": "its one large product (the decoder folded into the head, 4608 -> 256) in int8 moved the commands by "
    "up to 0.2 m/s (2.3 deg) over recorded flights, above the 0.15 m/s tolerance",
}
# smaller products gain nothing from int8 at batch 1: the per-call input quantisation costs more than it saves
MIN_WEIGHT_ELEMENTS = 16_384
PER_CHANNEL = True


def _large_products(model: onnx.ModelProto, min_weight_elements: int) -> list[str]:
    """Names of the MatMul nodes whose second input is an initializer with at least ``min_weight_elements``."""
    sizes = {init.name: numpy_helper.to_array(init).size for init in model.graph.initializer}
    return [
        node.name
        for node in model.graph.node
        if node.op_type == "MatMul" and sizes.get(node.input[1], 0) >= min_weight_elements
    ]


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


def quantize_int8(model_bytes: bytes, min_weight_elements: int = MIN_WEIGHT_ELEMENTS) -> bytes:
    """The int8 version of an exported vitfly policy (its large products; none for ``FLOAT32_MODELS``);
    metadata kept, plus ``vitfly.precision = int8`` and ``vitfly.int8_products`` (how many were quantised)."""
    from onnxruntime.quantization import QuantType, quantize_dynamic

    model = onnx.load_from_string(model_bytes)
    metadata = {p.key: p.value for p in model.metadata_props}
    nodes = []
    if metadata.get("vitfly.model") not in FLOAT32_MODELS:
        _gemms_as_matmuls(model, min_weight_elements)
        nodes = _large_products(model, min_weight_elements)
    with tempfile.TemporaryDirectory(prefix="vitfly-int8-") as tmp:
        out = Path(tmp) / "int8.onnx"
        if nodes:
            quantize_dynamic(model, out, op_types_to_quantize=["MatMul", "Gemm"], nodes_to_quantize=nodes,
                             weight_type=QuantType.QInt8, per_channel=PER_CHANNEL, reduce_range=False)  # fmt: skip
            model = onnx.load(out)
    onnx.checker.check_model(model)
    metadata["vitfly.precision"] = "int8"
    metadata["vitfly.int8_products"] = str(len(nodes))
    del model.metadata_props[:]
    for key, value in metadata.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    return model.SerializeToString()
