"""A Lightning callback that flies the network being trained in a few held-out scenes every N epochs.

Validation loss alone does not say whether a policy flies (a constant forward command already scores a
validation cosine of 0.977), so this callback logs, after every ``every_n_epochs``-th validation epoch:

- ``closed_loop/success``: share of trials without a collision (the paper's success);
- ``closed_loop/goal``: share of trials that reached x = goal;
- ``closed_loop/collisions``: collision entries per trial.

The scenes are the evaluation sweep's (``derive_scene_seed(seed, env, k)``, k < trials), flown at each
of ``speeds`` with a copy of the network on the CPU, so training state is untouched. It needs the
simulator, so it lives here rather than in ``vitfly.zoo``. Use it from a fit YAML::

    trainer:
      callbacks:
        - class_path: vitfly.workflows.closed_loop_check.ClosedLoopCheck
          init_args: {every_n_epochs: 5, trials: 4, speeds: [3.0, 5.0]}

or pass ``ClosedLoopCheck(...)`` in ``callbacks`` of ``vitfly.training.train_policy``.
"""

from __future__ import annotations

import copy

import lightning as L
import numpy as np

from vitfly.errors import VitflyError


class ClosedLoopCheck(L.Callback):
    """Fly ``trials`` held-out scenes of ``env`` at each of ``speeds`` (m/s) every ``every_n_epochs`` epochs.

    Args:
        every_n_epochs: fly after every N-th validation epoch (1: every one).
        env: ``spheres``, ``trees`` or ``window``.
        preset: scene density preset.
        speeds: desired speeds, m/s.
        trials: scenes per speed.
        seed: sweep seed of the scenes (default 1000, the evaluation's: scenes the collection never used).
        timeout_s: trial timeout, s (None: the simulator's default, scaled with speed).
        threads: torch threads while flying (the training's own setting is restored after).
    """

    def __init__(self, every_n_epochs: int = 5, env: str = "spheres", preset: str = "medium",
                 speeds: list[float] | None = None, trials: int = 4, seed: int = 1000,
                 timeout_s: float | None = None, threads: int = 1) -> None:
        super().__init__()
        if every_n_epochs < 1 or trials < 1 or threads < 1:
            raise VitflyError("ClosedLoopCheck: every_n_epochs, trials and threads must be >= 1")
        self.every_n_epochs = every_n_epochs
        self.env = env
        self.preset = preset
        self.speeds = [float(s) for s in (speeds or [3.0, 5.0])]
        self.trials = trials
        self.seed = seed
        self.timeout_s = timeout_s
        self.threads = threads
        self.history: list[dict] = []  # one entry per check: epoch and the three numbers

    def fly(self, net) -> dict[str, float]:
        """Fly the checks with ``net`` (eval mode, CPU); returns success, goal and collisions per trial."""
        import torch

        from vitfly.eval.learned_policy import LearnedPolicy
        from vitfly.eval.sweep import derive_scene_seed
        from vitfly.sim.rollout import RolloutConfig, TaskConfig, run_episodes
        from vitfly.sim.scenes import make_scene

        task = TaskConfig() if self.timeout_s is None else TaskConfig(timeout_s=self.timeout_s,
                                                                      timeout_speed_factor=0.0)
        scenes, speeds = [], []
        for k in range(self.trials):
            scene = make_scene(self.env, self.preset, derive_scene_seed(self.seed, self.env, k))
            for speed in self.speeds:
                scenes.append(scene)
                speeds.append(speed)
        previous = torch.get_num_threads()
        torch.set_num_threads(self.threads)
        try:
            results = run_episodes(scenes, speeds, LearnedPolicy(net), RolloutConfig(task=task))
        finally:
            torch.set_num_threads(previous)
        collisions = np.array([r.summary.n_collisions for r in results], dtype=float)
        return {"success": float(np.mean(collisions == 0)),
                "goal": float(np.mean([r.summary.reached_goal for r in results])),
                "collisions": float(collisions.mean())}

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.sanity_checking or (trainer.current_epoch + 1) % self.every_n_epochs:
            return
        if not trainer.is_global_zero:  # one rank flies and logs
            return
        numbers = self.fly(copy.deepcopy(pl_module.net).cpu().eval())
        self.history.append({"epoch": trainer.current_epoch, **numbers})
        for key, value in numbers.items():
            pl_module.log(f"closed_loop/{key}", value, rank_zero_only=True)
