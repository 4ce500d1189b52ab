"""Physics back ends: what integrates the drones' rigid-body motion.

Two implementations of one contract (:class:`vitfly.sim.physics.base.Fleet`, which fixes the
integration step), interchangeable to rounding:

- ``"pybullet"``: pybullet in DIRECT mode, the reference. A dependency wherever PyPI has a wheel
  (pybullet 3.2.7: CPython <= 3.11 on Linux x86_64).
- ``"native"``: vitfly's integrator of the same airframe and scheme, numpy only, all lockstep
  drones in one array step; for every other Python and machine, and faster.

``"auto"`` (every config's default) is pybullet where it is installed, else native, which is said
once on stderr. Every dataset (``config.collect.physics``) and trial record (``extra.physics``)
names the back end that produced it.

Example::

    from vitfly.sim.physics import make_fleet
    with make_fleet("native", num_drones=16) as fleet:
        fleet.reset(np.tile([0.0, 0.0, 3.5], (16, 1)))
"""

from __future__ import annotations

import importlib.util
import os
import platform
import sys

from vitfly.errors import VitflyError
from vitfly.sim.physics.base import Fleet
from vitfly.sim.quadrotor import Airframe

PHYSICS_BACKENDS = ("pybullet", "native")
PHYSICS_CHOICES = ("auto", *PHYSICS_BACKENDS)
# set once the "using native" notice is out, so worker processes (which inherit it) stay quiet
_NOTICE_ENV = "VITFLY_PHYSICS_NOTICE_SHOWN"
_PYBULLET: list[bool] = []  # cached answer of pybullet_available()


def pybullet_available() -> bool:
    """True when pybullet can be imported here (looked up, not imported)."""
    if not _PYBULLET:
        _PYBULLET.append(importlib.util.find_spec("pybullet") is not None)
    return _PYBULLET[0]


def _where() -> str:
    return f"CPython {platform.python_version()} on {platform.system()} {platform.machine()}"


def resolve_physics(name: str | None = "auto", source: str = "physics") -> str:
    """The back end a run uses: ``name`` checked, ``"auto"`` / None made concrete.

    Raises VitflyError (one line naming ``source``) for an unknown name, or for ``"pybullet"``
    where pybullet is not installed.
    """
    if name is None or name == "auto":
        if pybullet_available():
            return "pybullet"
        if not os.environ.get(_NOTICE_ENV):
            os.environ[_NOTICE_ENV] = "1"
            print(
                f"vitfly: pybullet is not installed ({_where()}; PyPI has pybullet wheels only for CPython <= 3.11 "
                "on Linux x86_64), so the simulator uses vitfly's native physics back end (the same airframe and "
                "integration scheme; --physics native says so explicitly)",
                file=sys.stderr,
            )
        return "native"
    if name not in PHYSICS_BACKENDS:
        raise VitflyError(f"{source}: physics back end {name!r} unknown; expected one of {', '.join(PHYSICS_CHOICES)}")
    if name == "pybullet" and not pybullet_available():
        raise VitflyError(
            f"{source}: physics back end 'pybullet' is not installed ({_where()}; PyPI has wheels only for "
            "CPython <= 3.11 on Linux x86_64, elsewhere pip compiles Bullet); use physics 'native' or 'auto'"
        )
    return name


def make_fleet(name: str | None, num_drones: int, airframe: Airframe | None = None, physics_hz: float = 240.0,
               **kwargs) -> Fleet:
    """A fleet of ``num_drones`` drones on back end ``name`` ("pybullet", "native" or "auto")."""
    name = resolve_physics(name)
    if name == "pybullet":
        from vitfly.sim.physics.bullet import PybulletFleet

        return PybulletFleet(num_drones, airframe, physics_hz, **kwargs)
    from vitfly.sim.physics.native import NativeFleet

    return NativeFleet(num_drones, airframe, physics_hz, **kwargs)


__all__ = ["Fleet", "PHYSICS_BACKENDS", "PHYSICS_CHOICES", "make_fleet", "pybullet_available", "resolve_physics"]
