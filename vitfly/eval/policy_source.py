"""What ``--policy`` names, as a picklable recipe that each worker process builds once.

``expert`` and ``straight`` are the simulator's built-in policies; ``pretrained:NAME`` is a network
published in the weights directory (``vitfly.zoo.pretrained``); anything else is a checkpoint path: a
vitfly/Lightning checkpoint, or an original-project state dict with ``arch``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from vitfly.errors import VitflyError

BUILTIN = ("expert", "straight")


@dataclass(frozen=True)
class PolicySource:
    spec: str  # "expert", "straight", "pretrained:NAME" or a checkpoint path
    arch: str | None = None  # architecture of an original-project checkpoint
    backend: str = "eager"  # "eager" or "onnxruntime" (learned policies)
    device: str = "cpu"
    threads: int = 1  # ONNX Runtime intra-op threads

    @property
    def is_builtin(self) -> bool:
        return self.spec in BUILTIN

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
        if self.is_pretrained:
            if self.arch is not None:
                raise VitflyError(f"--arch {self.arch} only applies to original checkpoints, not to {self.spec}")
            from vitfly.zoo.pretrained import manifest_entry, pretrained_name

            manifest_entry(pretrained_name(self.spec))  # the manifest lists it; the file is checked on loading
            return
        if not Path(self.spec).is_file():
            raise VitflyError(f"--policy {self.spec}: no such checkpoint file "
                              "(or use 'expert', 'straight' or 'pretrained:NAME')")

    def trained_sensor(self) -> dict | None:
        """The sensor a checkpoint was trained with ({depth_max_m, camera, control_hz}); None for the built-in
        policies and for checkpoints that do not record one."""
        if self.is_builtin:
            return None
        if self.is_pretrained:  # published weights carry their checkpoint's sensor in the manifest
            from vitfly.zoo.pretrained import manifest_entry, pretrained_name

            return manifest_entry(pretrained_name(self.spec)).get("sensor")
        from vitfly.zoo.checkpoint import load_sensor

        return load_sensor(self.spec)

    def load_network(self):
        if self.is_pretrained:
            from vitfly.zoo.pretrained import load_pretrained

            return load_pretrained(self.spec)
        from vitfly.zoo import load_network

        return load_network(self.spec, arch=self.arch)

    def build(self):
        """The policy object for the rollout engine."""
        if self.is_builtin:
            from vitfly.sim.policies import make_builtin_policy

            return make_builtin_policy(self.spec)
        from vitfly.eval.learned_policy import LearnedPolicy

        net = self.load_network()
        step_fn = None
        if self.backend == "onnxruntime":
            from vitfly.deploy.onnx import OnnxPolicyRunner

            step_fn = OnnxPolicyRunner(net, threads=self.threads)  # exported on the fly, checked against eager
        return LearnedPolicy(net, device=self.device, step_fn=step_fn)
