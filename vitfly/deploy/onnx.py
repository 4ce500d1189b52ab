"""ONNX export of zoo networks and an ONNX Runtime runner with the zoo's call contract.

The exported graph takes ``depth`` (B, 1, 1, 60, 90), ``desired_speed`` (B, 1, 1) m/s and ``quat``
(B, 1, 4) (w, x, y, z) -- one control tick per call, B dynamic -- and, for recurrent networks, the
LSTM state ``h0``/``c0`` (layers, B, hidden); it returns ``velocity`` (B, 1, 3) (command / desired
speed) and ``hn``/``cn``. Model facts (registry name, use_state, state shape) travel in the ONNX
metadata so ``OnnxPolicyRunner`` needs nothing but the file.
"""

from __future__ import annotations

import contextlib
import io
import os
import warnings

import numpy as np
import torch
from torch import nn

from vitfly.atomic import write_bytes
from vitfly.deploy.optimize import inference_copy
from vitfly.deploy.quantize import PRECISIONS, quantize_int8
from vitfly.errors import VitflyError
from vitfly.zoo.base import IMAGE_HEIGHT, IMAGE_WIDTH

INPUTS = ("depth", "desired_speed", "quat")
STATE_INPUTS = ("h0", "c0")
OUTPUTS = ("velocity",)
STATE_OUTPUTS = ("hn", "cn")
EXPORT_BATCH = 2  # example batch for tracing; 1 would be specialised away by torch.export
# largest output difference to eager accepted by the check before use, relative to max(1, output scale):
# float32 graphs differ by rounding only; int8 products by their quantisation (commands: vitfly.eval.agreement)
CHECK_ATOL = {"fp32": 1e-4, "int8": 5e-2}


class _FlatSignature(nn.Module):
    """Positional tensors in, a flat tuple out: what the ONNX exporter wants."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, depth, desired_speed, quat, h0=None, c0=None):
        hidden = None if h0 is None else (h0, c0)
        velocity, hidden = self.net(depth, desired_speed, quat, hidden)
        return velocity if hidden is None else (velocity, hidden[0], hidden[1])


def example_inputs(net: nn.Module, batch_size: int = 1, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """Random inputs of one control tick: depth in [0, 1], speeds 3-7 m/s, unit quaternions."""
    g = torch.Generator().manual_seed(seed)
    depth = torch.rand(batch_size, 1, 1, IMAGE_HEIGHT, IMAGE_WIDTH, generator=g)
    speed = 3.0 + 4.0 * torch.rand(batch_size, 1, 1, generator=g)
    level = torch.tensor([[[1.0, 0.0, 0.0, 0.0]]])  # near-level flight, slightly perturbed
    quat = torch.nn.functional.normalize(level + 0.1 * torch.randn(batch_size, 1, 4, generator=g), dim=-1)
    return depth, speed, quat


def _state_shape(net: nn.Module) -> tuple[int, int] | None:
    hidden = net.initial_hidden(1) if getattr(net, "is_recurrent", False) else None
    return None if hidden is None else (hidden[0].shape[0], hidden[0].shape[2])


def export_onnx_bytes(
    net: nn.Module,
    *,
    name: str = "",
    use_state: bool | None = None,
    optimize: bool = True,
    opset: int | None = None,
    batch_size: int | None = None,
    precision: str = "fp32",
    calibration_depth: np.ndarray | None = None,
) -> bytes:
    """The ONNX model of ``net`` (a zoo network) as bytes; see the module docstring for the signature.

    ``batch_size`` None gives a dynamic batch axis; an int fixes it (a leaner graph: batch-1 deployment).
    ``precision`` "int8" quantises the large matrix products (``vitfly.deploy.quantize``) and, with
    ``optimize``, takes the tanh approximation of GELU (``inference_copy``). Given ``calibration_depth``
    (N, 60, 90) frames in [0, 1] (recorded flights), the int8 ViTs also run their mix-FFNs as int8
    convolutions whose activation ranges those frames fix; without, the mix-FFNs stay float32.
    """
    if precision not in PRECISIONS:
        raise VitflyError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    net = net.eval()
    state_shape = _state_shape(net)
    int8 = precision == "int8"
    fuse_ffn = int8 and calibration_depth is not None
    graph_net = inference_copy(net, approximate_gelu=int8, fuse_ffn=fuse_ffn) if optimize else net
    example_batch = EXPORT_BATCH if batch_size is None else batch_size
    args = example_inputs(net, example_batch)
    dynamic: dict[str, dict[int, object]] | None = None
    if batch_size is None:
        batch = torch.export.Dim("batch", min=1, max=4096)
        dynamic = {"depth": {0: batch}, "desired_speed": {0: batch}, "quat": {0: batch}}
    input_names, output_names = list(INPUTS), list(OUTPUTS)
    if state_shape is not None:
        layers, size = state_shape
        args = (*args, torch.zeros(layers, example_batch, size), torch.zeros(layers, example_batch, size))
        if dynamic is not None:
            dynamic.update({"h0": {1: batch}, "c0": {1: batch}})
        input_names += STATE_INPUTS
        output_names += STATE_OUTPUTS
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()), torch.no_grad():
        warnings.simplefilter("ignore")
        program = torch.onnx.export(
            _FlatSignature(graph_net).eval(),
            args,
            dynamo=True,
            input_names=input_names,
            output_names=output_names,
            dynamic_shapes=dynamic,
            opset_version=opset,
            optimize=True,
            external_data=False,
            verbose=False,
        )
    model = program.model_proto
    meta = {
        "vitfly.model": name or getattr(net, "model_name", "") or type(net).__name__,
        "vitfly.use_state": str(bool(getattr(net, "use_state", True) if use_state is None else use_state)),
        "vitfly.recurrent": str(state_shape is not None),
        "vitfly.state_layers": str(state_shape[0] if state_shape else 0),
        "vitfly.state_size": str(state_shape[1] if state_shape else 0),
        "vitfly.params": str(sum(p.numel() for p in net.parameters())),
        "vitfly.optimized": str(optimize),
        "vitfly.batch_size": str(batch_size or 0),
        "vitfly.precision": "fp32",
    }
    del model.metadata_props[:]
    for key, value in meta.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    data = model.SerializeToString()
    return quantize_int8(data, calibration_depth=calibration_depth if fuse_ffn else None) if int8 else data


def export_onnx(
    net: nn.Module,
    path: str | os.PathLike,
    *,
    name: str = "",
    optimize: bool = True,
    opset: int | None = None,
    batch_size: int | None = None,
    check: bool = True,
    atol: float | None = None,
    precision: str = "fp32",
    calibration_depth: np.ndarray | None = None,
) -> float | None:
    """Write ``net`` as ONNX to ``path`` atomically; with ``check``, first verify it against eager.

    Returns the largest output difference found by the check (None without check). Raises VitflyError
    and writes nothing if ONNX Runtime's outputs differ from eager by more than ``atol`` (default
    ``CHECK_ATOL[precision]``; relative to the output magnitude when it exceeds 1).
    """
    data = export_onnx_bytes(net, name=name, optimize=optimize, opset=opset, batch_size=batch_size,
                             precision=precision, calibration_depth=calibration_depth)  # fmt: skip
    diff = None
    if check:
        atol = CHECK_ATOL[precision] if atol is None else atol
        diff = OnnxPolicyRunner(data).check_against(net, atol=atol, batch_size=batch_size or 2)
    write_bytes(path, data)
    return diff


# ONNX Runtime fusions that make these small graphs slower: SkipLayerNormalization (residual add + LayerNorm)
# runs the ViT's 32/64-channel post-norms about 3x slower than the separate Add and LayerNormalization
DISABLED_OPTIMIZERS = ["SkipLayerNormFusion"]


def session_options(threads: int = 1):
    """ONNX Runtime options for low-latency single-stream inference."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.log_severity_level = 3
    return options


class OnnxPolicyRunner:
    """Run an exported policy with ONNX Runtime, with the zoo's call contract.

    ``runner(depth[B, T, 1, 60, 90], desired_speed[B, T, 1], quat[B, T, 4], hidden=None)
    -> (velocity[B, T, 3], hidden)``; numpy in gives numpy out, torch in gives torch out. T > 1 runs
    the ticks one after another, carrying the recurrent state. ``path_or_net`` is an .onnx file, ONNX
    bytes, or a zoo network (exported on the fly in ``precision``, then checked against eager within
    ``CHECK_ATOL[precision]``; ``calibration_depth`` as for ``export_onnx_bytes``).
    """

    def __init__(
        self,
        path_or_net: str | os.PathLike | bytes | nn.Module,
        threads: int = 1,
        *,
        providers: list[str] | None = None,
        optimize: bool = True,
        precision: str = "fp32",
        calibration_depth: np.ndarray | None = None,
    ) -> None:
        import onnxruntime as ort

        if isinstance(path_or_net, nn.Module):
            model = export_onnx_bytes(path_or_net, optimize=optimize, precision=precision,
                                      calibration_depth=calibration_depth)  # fmt: skip
            source = type(path_or_net).__name__
        elif isinstance(path_or_net, bytes):
            model, source = path_or_net, "<onnx bytes>"
        else:
            source = os.fspath(path_or_net)
            if not os.path.isfile(source):
                raise VitflyError(f"{source}: no such ONNX file")
            model = source
        try:
            self.session = ort.InferenceSession(
                model,
                session_options(threads),
                providers=providers or ["CPUExecutionProvider"],
                disabled_optimizers=DISABLED_OPTIMIZERS,
            )
        except Exception as err:
            raise VitflyError(f"{source}: ONNX Runtime cannot load it: {str(err).splitlines()[0][:200]}") from None
        meta = self.session.get_modelmeta().custom_metadata_map
        if "vitfly.recurrent" not in meta:
            raise VitflyError(f"{source}: not a vitfly policy export (no vitfly.* metadata); use `vitfly export`")
        self.source = source
        self.model_name = meta["vitfly.model"]
        self.is_recurrent = meta["vitfly.recurrent"] == "True"
        self.state_shape = (int(meta["vitfly.state_layers"]), int(meta["vitfly.state_size"]))
        self.params = int(meta.get("vitfly.params", 0))
        self.precision = meta.get("vitfly.precision", "fp32")
        self._outputs = list(OUTPUTS) + (list(STATE_OUTPUTS) if self.is_recurrent else [])
        if isinstance(path_or_net, nn.Module):
            self.check_against(path_or_net, atol=CHECK_ATOL.get(self.precision, CHECK_ATOL["fp32"]))

    def initial_hidden(self, batch_size: int) -> tuple[np.ndarray, np.ndarray]:
        """Zero LSTM state (h, c), each (layers, B, hidden) float32."""
        layers, size = self.state_shape
        zeros = np.zeros((layers, batch_size, size), dtype=np.float32)
        return zeros, zeros.copy()

    def step(self, depth: np.ndarray, desired_speed: np.ndarray, quat: np.ndarray, hidden=None):
        """One tick, numpy float32 in and out: depth (B, 1, 1, 60, 90) -> (velocity (B, 1, 3), hidden)."""
        feed = {"depth": depth, "desired_speed": desired_speed, "quat": quat}
        if self.is_recurrent:
            if hidden is None:
                hidden = self.initial_hidden(depth.shape[0])
            feed["h0"], feed["c0"] = hidden
            velocity, h, c = self.session.run(self._outputs, feed)
            return velocity, (h, c)
        return self.session.run(self._outputs, feed)[0], None

    def bind(self, batch_size: int = 1) -> BoundStep:
        """A zero-copy stepper for a fixed batch (ONNX Runtime I/O binding); see ``BoundStep``."""
        return BoundStep(self, batch_size)

    def __call__(self, depth, desired_speed, quat, hidden=None):
        as_torch = isinstance(depth, torch.Tensor)
        arrays = [_as_float32(x) for x in (depth, desired_speed, quat)]
        shape = arrays[0].shape
        if len(shape) != 5 or shape[2:] != (1, IMAGE_HEIGHT, IMAGE_WIDTH):
            raise VitflyError(f"depth: expected shape (B, T, 1, {IMAGE_HEIGHT}, {IMAGE_WIDTH}), got {tuple(shape)}")
        b, t = shape[:2]
        if arrays[1].shape != (b, t, 1):
            raise VitflyError(f"desired_speed: expected shape ({b}, {t}, 1) = (B, T, 1), got {arrays[1].shape}")
        if arrays[2].shape != (b, t, 4):
            raise VitflyError(f"quat: expected shape ({b}, {t}, 4) = (B, T, 4), got {arrays[2].shape}")
        if hidden is not None:
            hidden = tuple(_as_float32(x) for x in hidden)
            expected = (self.state_shape[0], b, self.state_shape[1])
            if len(hidden) != 2 or any(x.shape != expected for x in hidden):
                raise VitflyError(f"hidden: expected (h, c), each of shape {expected} = (layers, B, hidden)")
        if not self.is_recurrent and t > 1:  # frames are independent: one call over B*T
            flat = [a.reshape(b * t, 1, *a.shape[2:]) for a in arrays]
            velocity = self.step(*flat)[0].reshape(b, t, 3)
        else:
            steps = []
            for i in range(t):
                v, hidden = self.step(*(np.ascontiguousarray(a[:, i : i + 1]) for a in arrays), hidden)
                steps.append(v)
            velocity = steps[0] if t == 1 else np.concatenate(steps, axis=1)
        if as_torch:
            velocity = torch.from_numpy(velocity)
            hidden = None if hidden is None else tuple(torch.from_numpy(x) for x in hidden)
        return velocity, hidden

    def check_against(self, net: nn.Module, atol: float = 1e-4, steps: int = 4, batch_size: int = 2) -> float:
        """Largest difference to eager ``net`` over a few carried-state ticks; VitflyError if above tolerance.

        The tolerance is ``atol`` times max(1, largest eager output magnitude) -- randomly initialised
        networks can have outputs far above 1, where float rounding alone exceeds an absolute 1e-4.
        """
        net = net.eval()
        hidden_ref, hidden = None, None
        worst, scale = 0.0, 1.0
        with torch.inference_mode():
            for step in range(steps):
                inputs = example_inputs(net, batch_size, seed=step)
                ref, hidden_ref = net(*inputs, hidden_ref)
                out, hidden = self(*inputs, hidden)
                scale = max(scale, float(ref.abs().max()))
                worst = max(worst, float((out - ref).abs().max()))
                if hidden_ref is not None:
                    worst = max(worst, float((hidden[1] - hidden_ref[1]).abs().max()))
        if not worst <= atol * scale:
            raise VitflyError(
                f"{self.source}: ONNX Runtime output differs from eager by {worst:.3g} "
                f"(tolerance {atol * scale:.3g}); refusing to use this export"
            )
        return worst


def _as_float32(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.ascontiguousarray(x, dtype=np.float32)


class BoundStep:
    """One control tick per call on pre-allocated, pre-bound buffers (the lowest per-call overhead).

    Write the tick's observation into ``depth`` (B, 1, 1, 60, 90), ``desired_speed`` (B, 1, 1) and
    ``quat`` (B, 1, 4) (e.g. ``np.copyto``), call, read ``velocity`` (B, 1, 3). The recurrent state
    stays inside and alternates between two buffer pairs; ``reset()`` zeroes it (a new flight).
    """

    def __init__(self, runner: OnnxPolicyRunner, batch_size: int = 1) -> None:
        self.runner = runner
        self.depth = np.zeros((batch_size, 1, 1, IMAGE_HEIGHT, IMAGE_WIDTH), dtype=np.float32)
        self.desired_speed = np.zeros((batch_size, 1, 1), dtype=np.float32)
        self.quat = np.zeros((batch_size, 1, 4), dtype=np.float32)
        self.quat[..., 0] = 1.0
        self.velocity = np.zeros((batch_size, 1, 3), dtype=np.float32)
        self._binding = runner.session.io_binding()
        for name, array in (("depth", self.depth), ("desired_speed", self.desired_speed), ("quat", self.quat)):
            self._binding.bind_cpu_input(name, array)
        self._bind_output("velocity", self.velocity)
        self._states = None
        if runner.is_recurrent:
            self._states = [runner.initial_hidden(batch_size), runner.initial_hidden(batch_size)]
            self._current = 0
            self._bind_state()

    def _bind_output(self, name: str, array: np.ndarray) -> None:
        self._binding.bind_output(name, "cpu", 0, np.float32, list(array.shape), array.ctypes.data)

    def _bind_state(self) -> None:
        (h_in, c_in), (h_out, c_out) = self._states[self._current], self._states[1 - self._current]
        self._binding.bind_cpu_input("h0", h_in)
        self._binding.bind_cpu_input("c0", c_in)
        self._bind_output("hn", h_out)
        self._bind_output("cn", c_out)

    @property
    def hidden(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The current LSTM state (h, c) (None for feed-forward networks)."""
        return None if self._states is None else self._states[self._current]

    def reset(self) -> None:
        if self._states is not None:
            for pair in self._states:
                for array in pair:
                    array.fill(0.0)

    def __call__(self) -> np.ndarray:
        self.runner.session.run_with_iobinding(self._binding)
        if self._states is not None:  # the new state becomes the next call's input
            self._current = 1 - self._current
            self._bind_state()
        return self.velocity
