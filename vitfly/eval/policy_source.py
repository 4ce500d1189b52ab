"""What ``--policy`` names, as a picklable recipe that each worker process builds once.

``expert`` and ``straight`` are the simulator's built-in policies; ``pretrained:NAME`` is a network
published in the weights directory (``vitfly.zoo.pretrained``); ``modular:NAME`` is one of the modular
baselines (``vitfly.planners``, options from ``planner_config`` or the shipped ``configs/planners.yaml``);
anything else is a checkpoint path: a vitfly/Lightning checkpoint, or an original-project state dict with ``arch``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from vitfly.devices import check_torch_device
from vitfly.errors import VitflyError
from vitfly.sim.camera import CameraConfig

BUILTIN = ("expert", "straight")
MODULAR_PREFIX = "modular:"


@dataclass(frozen=True)
class PolicySource:
    spec: str  # "expert", "straight", "pretrained:NAME" or a checkpoint path
    arch: str | None = None  # architecture of an original-project checkpoint
    backend: str = "eager"  # "eager", "compiled", "onnxruntime" or "onnxruntime-int8" (learned policies)
    device: str = "cpu"  # the learned policy's network: "cpu" or "cuda[:N]"
    threads: int = 1  # ONNX Runtime intra-op threads
    planner_config: str | None = None  # modular:NAME: the planners YAML (None: the shipped configs/planners.yaml)
    camera: CameraConfig | None = None  # modular:NAME: the camera flown with (its rays back-project the depth)

    @property
    def is_builtin(self) -> bool:
        return self.spec in BUILTIN

    @property
    def is_modular(self) -> bool:
        return self.spec.startswith(MODULAR_PREFIX)

    def planner_options(self):
        """The ``PlannerOptions`` of ``modular:NAME`` (one VitflyError line for an unknown name or a bad option)."""
        from vitfly.planners import load_planner_options

        return load_planner_options(self.spec[len(MODULAR_PREFIX):], self.planner_config)

    @property
    def is_pretrained(self) -> bool:
        from vitfly.zoo.pretrained import is_pretrained_spec

        return is_pretrained_spec(self.spec)

    def check(self) -> None:
        """Fail early, in the parent process, with one line naming the bad input."""
        if self.is_builtin:
            if self.arch is not None:
                raise VitflyError(f"--arch {self.arch} only applies to checkpoints, not to policy {self.spec!r}")
            return
        if self.is_modular:
            if self.arch is not None:
                raise VitflyError(f"--arch {self.arch} only applies to checkpoints, not to policy {self.spec!r}")
            self.planner_options()
            return
        if self.planner_config is not None:
            raise VitflyError(f"--planner-config only applies to modular:NAME policies, not to {self.spec!r}")
        if self.is_pretrained:
            if self.arch is not None:
                raise VitflyError(f"--arch {self.arch} only applies to original checkpoints, not to {self.spec}")
            from vitfly.zoo.pretrained import manifest_entry, pretrained_name

            manifest_entry(pretrained_name(self.spec))  # the manifest lists it; the file is checked on loading
            check_device(self.device, self.backend)
            return
        if not Path(self.spec).is_file():
            raise VitflyError(f"--policy {self.spec}: no such checkpoint file "
                              "(or use 'expert', 'straight' or 'pretrained:NAME')")
        check_device(self.device, self.backend)

    def trained_sensor(self) -> dict | None:
        """The sensor a checkpoint was trained with ({depth_max_m, camera, control_hz}); None for the built-in
        policies, the modular planners and for checkpoints that do not record one."""
        if self.is_builtin or self.is_modular:
            return None
        if self.is_pretrained:  # published weights carry their checkpoint's sensor in the manifest
            from vitfly.zoo.pretrained import manifest_entry, pretrained_name

            return manifest_entry(pretrained_name(self.spec)).get("sensor")
        from vitfly.zoo.checkpoint import load_sensor

        return load_sensor(self.spec)

    def load_network(self):
        from vitfly.zoo.pretrained import load_weights

        return load_weights(self.spec, arch=self.arch)

    def build(self):
        """The policy object for the rollout engine."""
        if self.is_builtin:
            from vitfly.sim.policies import make_builtin_policy

            return make_builtin_policy(self.spec)
        if self.is_modular:
            from vitfly.planners import ModularPolicy

            return ModularPolicy(self.planner_options(), self.camera)
        from vitfly.eval.learned_policy import LearnedPolicy

        net = self.load_network()
        step_fn = None
        if self.backend.startswith("onnxruntime"):
            from vitfly.deploy.onnx import OnnxPolicyRunner

            precision = "int8" if self.backend == "onnxruntime-int8" else "fp32"
            providers = ["CUDAExecutionProvider"] if self.device.startswith("cuda") else None
            calibration = None
            if precision == "int8":
                from vitfly.eval.agreement import calibration_depth
                from vitfly.eval.latency import needs_calibration

                calibration = calibration_depth() if needs_calibration(net) else None
            # exported on the fly, checked against eager; ONNX Runtime takes host arrays whatever its provider
            step_fn = OnnxPolicyRunner(net, threads=self.threads, providers=providers, precision=precision,
                                       calibration_depth=calibration)  # fmt: skip
            return LearnedPolicy(net, device="cpu", step_fn=step_fn)
        if self.backend == "compiled":  # encoder via torch.compile (without a compiler: one warning, eager)
            from vitfly.zoo import compile_encoder

            compile_encoder(net)
        return LearnedPolicy(net, device=self.device)


def check_device(device: str, backend: str = "eager") -> None:
    """One-line VitflyError unless ``device`` ("cpu", "cuda", "cuda:N") can run ``backend`` here."""
    import torch

    check_torch_device(device, "--device")
    if torch.device(device).type == "cpu":
        return
    if backend == "onnxruntime-int8":
        raise VitflyError(f"--backend {backend} runs on the CPU; with --device {device} use --backend eager")
    if backend == "onnxruntime":
        import onnxruntime as ort

        if "CUDAExecutionProvider" not in ort.get_available_providers():
            raise VitflyError(f"--backend onnxruntime --device {device} needs onnxruntime-gpu; or use --backend eager")
