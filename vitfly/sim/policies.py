"""Built-in policies for the rollout engine: the privileged expert, straight-ahead flight, and a mixture.

All follow :class:`vitfly.sim.rollout.Policy`: ``reset(num_envs)`` and ``__call__(obs)``. The expert and
straight flight return (N, 3) world-frame velocity commands (m/s) and never look at the depth image
(``needs_depth = False``). :class:`MixturePolicy` flies one of two policies per env and tick and labels
every tick with the expert's command (DAgger's data collection).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from vitfly.errors import VitflyError
from vitfly.sim.expert import ExpertConfig, ExpertObstacles, expert_command
from vitfly.sim.rollout import LabelledCommands, Observation


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


class MixturePolicy:
    """Flies the expert's command with probability ``beta`` and the student's otherwise, per env and per tick,
    and labels every tick with the expert's command (DAgger, Ross et al. 2011: beta_i of round i).

    At every tick each active env i draws u from U[0, 1) with its own generator and flies the expert's
    command iff u < beta (beta 1: always the expert; 0: always the student). Every active env draws at
    every tick whatever beta is, so env i's draws depend on its seed alone, not on the batch it flies in.
    Both policies run at every tick: the expert for the label, the student so that its recurrent state
    follows the flight as it would at deployment.

    Args:
        expert: the labelling policy (``ExpertPolicy``); its commands are the labels.
        student: the learned policy (e.g. ``vitfly.eval.learned_policy.LearnedPolicy``); None only with
            beta 1 (the expert flies every tick).
        beta: probability in [0, 1] that the expert's command is flown at a tick.
        seeds: env i's generator is ``np.random.default_rng(seeds[i])`` (one seed per env, e.g. per
            trajectory, so a trajectory's draws do not depend on its batch), or, given one int s,
            ``np.random.default_rng([s, i])``.

    Returns :class:`vitfly.sim.rollout.LabelledCommands` (command flown, expert label) per call.
    After a rollout, ``expert_ticks`` and ``ticks`` (N,) count the ticks each env flew the expert's
    command and the ticks it was active.
    """

    def __init__(self, expert, student, beta: float, seeds: int | Sequence = 0):
        beta = float(beta)
        if not 0.0 <= beta <= 1.0:
            raise VitflyError(f"MixturePolicy: beta must be a probability in [0, 1], got {beta}")
        if student is None and beta < 1.0:
            raise VitflyError(f"MixturePolicy: beta {beta} flies a student at some ticks, but no student was given")
        self.expert, self.student, self.beta, self.seeds = expert, student, beta, seeds
        self.needs_depth = any(bool(getattr(p, "needs_depth", True)) for p in (expert, student) if p is not None)
        self._rngs: list[np.random.Generator] = []
        self.expert_ticks = np.zeros(0, dtype=np.int64)
        self.ticks = np.zeros(0, dtype=np.int64)

    def reset(self, num_envs: int) -> None:
        if isinstance(self.seeds, int | np.integer):
            seeds = [[int(self.seeds), i] for i in range(num_envs)]
        else:
            seeds = list(self.seeds)
            if len(seeds) != num_envs:
                raise ValueError(f"MixturePolicy: {len(seeds)} seeds for {num_envs} envs")
        self._rngs = [np.random.default_rng(s) for s in seeds]
        self.expert.reset(num_envs)
        if self.student is not None:
            self.student.reset(num_envs)
        self.expert_ticks = np.zeros(num_envs, dtype=np.int64)
        self.ticks = np.zeros(num_envs, dtype=np.int64)

    def draw(self, active: np.ndarray) -> np.ndarray:
        """One U[0, 1) draw per active env (NaN for inactive ones), from each env's own generator."""
        u = np.full(len(active), np.nan)
        for i in np.flatnonzero(active):
            u[i] = self._rngs[i].random()
        return u

    def choose(self, active: np.ndarray) -> np.ndarray:
        """(N,) bool: the active envs that fly the expert's command this tick; drawn and counted."""
        active = np.asarray(active, dtype=bool)
        expert_flies = active & (self.draw(active) < self.beta)  # NaN < beta is False
        self.expert_ticks += expert_flies
        self.ticks += active
        return expert_flies

    def __call__(self, obs: Observation) -> LabelledCommands:
        label = np.asarray(self.expert(obs), dtype=np.float64)
        student = label if self.student is None else np.asarray(self.student(obs), dtype=np.float64)
        command = np.where(self.choose(obs.active)[:, None], label, student)
        return LabelledCommands(command=command, label=label)


BUILTIN_POLICIES = {"expert": ExpertPolicy, "straight": StraightPolicy}


def make_builtin_policy(name: str):
    """``expert`` or ``straight``; VitflyError for any other name."""
    try:
        return BUILTIN_POLICIES[name]()
    except KeyError:
        raise VitflyError(f"unknown built-in policy {name!r}; expected one of {', '.join(BUILTIN_POLICIES)}") from None
