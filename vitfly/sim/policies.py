"""Built-in policies for the rollout engine: the privileged expert and straight-ahead flight.

Both follow :class:`vitfly.sim.rollout.Policy`: ``reset(num_envs)`` and ``__call__(obs) -> (N, 3)``
world-frame velocity commands (m/s). Neither looks at the depth image (``needs_depth = False``).
"""

from __future__ import annotations

import numpy as np

from vitfly.errors import VitflyError
from vitfly.sim.expert import ExpertConfig, ExpertObstacles, expert_command
from vitfly.sim.rollout import Observation


class ExpertPolicy:
    """The privileged expert (:func:`vitfly.sim.expert.expert_command`) for every active env.

    Given the whole scene (``obs.scenes``), it keeps what ``config`` says Flightmare published:
    by default the 10 nearest objects within 10 m (a tree counts once). Without scenes, each row of
    ``obs.obstacles`` counts as one object.
    """

    needs_depth = False

    def __init__(self, config: ExpertConfig | None = None):
        self.config = config or ExpertConfig()
        self._views: dict[int, tuple[object, ExpertObstacles]] = {}

    def reset(self, num_envs: int) -> None:
        self._views = {}

    def _view(self, obs: Observation, i: int) -> ExpertObstacles:
        source = obs.scenes[i] if obs.scenes is not None else obs.obstacles[i]
        cached = self._views.get(i)
        if cached is None or cached[0] is not source:  # built once per scene (the cover is not free)
            if obs.scenes is not None:
                view = ExpertObstacles.from_scene(source)
            else:
                view = ExpertObstacles.from_spheres(source)
            cached = self._views[i] = (source, view)
        return cached[1]

    def __call__(self, obs: Observation) -> np.ndarray:
        out = np.zeros((len(obs.active), 3))
        for i in np.flatnonzero(obs.active):
            out[i] = expert_command(obs.position[i], self._view(obs, i), float(obs.desired_speed[i]), self.config)
        return out


class StraightPolicy:
    """Flies straight ahead: (desired_speed, 0, 0) m/s, world frame; the baseline without avoidance."""

    needs_depth = False

    def reset(self, num_envs: int) -> None:
        pass

    def __call__(self, obs: Observation) -> np.ndarray:
        out = np.zeros((len(obs.active), 3))
        out[:, 0] = obs.desired_speed
        return out


BUILTIN_POLICIES = {"expert": ExpertPolicy, "straight": StraightPolicy}


def make_builtin_policy(name: str):
    """``expert`` or ``straight``; VitflyError for any other name."""
    try:
        return BUILTIN_POLICIES[name]()
    except KeyError:
        raise VitflyError(f"unknown built-in policy {name!r}; expected one of {', '.join(BUILTIN_POLICIES)}") from None
