"""Which simulator engine flies the episodes: the numpy engine (the default) or the batched torch engine.

Both fly the same closed loop and return the same :class:`~vitfly.sim.rollout.EpisodeResult` objects;
in float64 on the CPU the batched engine reproduces the numpy engine with the native physics back end to
rounding (docs/simulator.md, "Batched engine"). :class:`SimEngine` is the choice as the commands take it
(``--sim``, ``--sim-device``, ``--sim-dtype`` and the same YAML fields), :func:`fly` runs either.

The choice is recorded with the results (``record()``: every trial record's ``extra.sim``, a dataset's
``config.collect.sim``) and is part of what keys them (``key()``): None for the numpy engine, so the keys
of everything flown before the batched engine existed stay what they were.

Example::

    engine = SimEngine("batched", device="cuda", dtype="float32").validate()
    results = fly(scenes, speeds, policy, RolloutConfig(physics=engine.physics("auto")), engine=engine)
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from vitfly.devices import check_torch_device
from vitfly.errors import VitflyError

SIM_ENGINES = ("numpy", "batched")
SIM_DTYPES = ("float64", "float32")


@dataclass(frozen=True)
class SimEngine:
    """name: "numpy" or "batched"; device ("cpu", "cuda", "cuda:1"), dtype ("float64", exact against the
    numpy engine, or "float32", faster) and compile (the hot kernels through ``torch.compile``: seconds once
    per process, then several times faster on a CPU) apply to the batched engine only."""

    name: str = "numpy"
    device: str = "cpu"
    dtype: str = "float64"
    compile: bool = False

    @property
    def batched(self) -> bool:
        return self.name == "batched"

    def validate(self, source: str = "config",
                 fields: tuple[str, ...] = ("sim", "sim_device", "sim_dtype", "sim_compile")) -> SimEngine:
        """Checked, or one VitflyError line naming ``source`` and the field (``fields``: their names there)."""
        sim, device, dtype, compile_ = fields
        if self.name not in SIM_ENGINES:
            raise VitflyError(f"{source}: field {sim!r} is {self.name!r}; expected one of {', '.join(SIM_ENGINES)}")
        if self.dtype not in SIM_DTYPES:
            raise VitflyError(f"{source}: field {dtype!r} is {self.dtype!r}; expected one of {', '.join(SIM_DTYPES)}")
        if not self.batched:
            # the numpy engine has no device or precision to choose: a setting here is a mistake, not a no-op
            for name, value, default in ((device, self.device, "cpu"), (dtype, self.dtype, "float64"),
                                         (compile_, self.compile, False)):
                if value != default:
                    raise VitflyError(f"{source}: field {name!r} is {value!r} but {sim!r} is 'numpy' (CPU, float64); "
                                      f"set {sim} batched to use it")
            return self
        check_torch_device(self.device, f"{source}: field {device!r}")
        return self

    def physics(self, name: str | None, source: str = "config: field 'physics'") -> str:
        """The physics back end to state for ``name`` ("auto", "native", "pybullet"): the batched engine is the
        native back end's integrator in torch, so it is "native" (pybullet is refused)."""
        from vitfly.sim.physics import resolve_physics

        if not self.batched:
            return resolve_physics(name, source)
        if name not in (None, "auto", "native"):
            raise VitflyError(f"{source}: {name!r} with the batched engine, which integrates the native back end's "
                              "airframe in torch; use physics native or auto")
        return "native"

    def record(self) -> dict:
        """What flew, as stored with the results."""
        if not self.batched:
            return {"engine": self.name}
        return {"engine": self.name, "device": self.device, "dtype": self.dtype, "compile": self.compile}

    def key(self) -> dict | None:
        """What decides the results beyond the rollout settings: None for the numpy engine; for the batched
        engine its dtype, whether compiled (fused kernels round differently) and the device's type (rounding
        differs between CPU and CUDA, not between cards)."""
        if not self.batched:
            return None
        import torch

        return {"engine": self.name, "device": torch.device(self.device).type, "dtype": self.dtype,
                "compile": self.compile}

    def settings(self):
        """The batched engine's :class:`~vitfly.sim.batched.rollout.BatchedSettings`."""
        import torch

        from vitfly.sim.batched.rollout import BatchedSettings

        return BatchedSettings(device=self.device, dtype=getattr(torch, self.dtype), compile=self.compile)


def fly(scenes: Sequence, speeds: Sequence[float], policy, config=None,
        on_episode_end: Callable | None = None, camera_seed: int | None = None,
        engine: SimEngine | None = None) -> list:
    """:func:`vitfly.sim.rollout.run_episodes` on the chosen engine (the numpy one by default), without
    gradients (train through :func:`vitfly.sim.batched.rollout.run_batched` itself)."""
    engine = engine or SimEngine()
    if not engine.batched:
        from vitfly.sim.rollout import run_episodes

        return run_episodes(scenes, speeds, policy, config, on_episode_end=on_episode_end, camera_seed=camera_seed)
    import torch

    from vitfly.sim.batched.rollout import run_batched

    with torch.no_grad():  # flights to score or to record want no gradients: a tenth less time per eager tick
        return run_batched(scenes, speeds, policy, config, on_episode_end=on_episode_end, camera_seed=camera_seed,
                           settings=engine.settings())
