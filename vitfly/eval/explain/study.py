"""The map numbers over many trials and their paired comparison: the paper's claim that the ConvNet's maps are
"diffuse" and "not consistent over time" where ViT+LSTM's are consistent and "on the edges of the object".

Every model is shown the same frames of each trial (the pilot flies, the models only look), so each trial gives
one value per model and map kind of the temporal consistency and the edge lift (``map_metrics``), and model A is
compared with model B on pairs: the mean over trials of A - B with a 95 % bootstrap interval over trials
(``vitfly.eval.paired.scene_bootstrap_interval``, one pair per scene, BCa). The claim "A's maps more consistent"
(or "more on edges") is decided when that interval excludes 0; the finding's verdict follows
``vitfly.eval.paired.claims_verdict``.

``cut_past_obstacles``: a trial's frames stop at the first tick at which the drone has passed the far face of
every obstacle (after that the frames hold the floor only and nothing is avoided), so the numbers describe the
approach and the avoidance.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from vitfly.errors import VitflyError
from vitfly.eval.explain.frames import TrialFrames
from vitfly.eval.explain.policies import ExplainedPolicy
from vitfly.eval.explain.run import explain_models
from vitfly.eval.paired import claim_side, claims_verdict, scene_bootstrap_interval
from vitfly.sim.scenes import Scene

STUDY_METRICS = ("consistency", "edge_lift")  # both: higher = the paper's "consistent" / "on edges"
TRIAL_COLUMNS = ("seed", "model", "map", "ticks", "consistency", "consistency_pairs", "edge_mass_share",
                 "edge_area_share", "edge_lift", "edge_ticks")


def far_x_m(scene: Scene) -> float:
    """The largest x (m, world) of any obstacle's solid (-inf for an empty scene)."""
    xs = [scene.spheres[:, 0] + scene.spheres[:, 3], scene.cylinders[:, 0] + scene.cylinders[:, 4],
          scene.boxes[:, 3]]
    xs = np.concatenate(xs)
    return float(xs.max()) if len(xs) else -math.inf


def ticks_before_passing(frames: TrialFrames, scene: Scene) -> int:
    """Ticks from the start until the drone's x first exceeds every obstacle's far face (all ticks if never)."""
    past = np.flatnonzero(frames.position[:, 0] > far_x_m(scene))
    return int(past[0]) if len(past) else len(frames)


def trial_rows(seed: int, frames: TrialFrames, policies: Sequence[ExplainedPolicy], device: str = "cpu") -> list[dict]:
    """One row per (model, map kind) of one trial: ``TRIAL_COLUMNS``."""
    rows = []
    for m in explain_models(policies, frames, device):
        for kind, numbers in m.metrics.items():
            rows.append({"seed": int(seed), "model": m.policy.label, "map": kind, "ticks": len(frames), **numbers})
    return rows


@dataclass(frozen=True)
class MapDifference:
    """Model ``a`` minus model ``b`` in ``metric`` of map kind ``map_kind``, over the trials where both have it."""

    metric: str
    map_kind: str
    a: str
    b: str
    trials: int
    mean_a: float
    mean_b: float
    diff: float
    low: float
    high: float

    @property
    def side(self) -> str:
        """The claim "a higher than b": for, against or undecided."""
        return claim_side(self.low, self.high)

    def text(self) -> str:
        return f"{self.diff:+.3f} [{self.low:+.3f}, {self.high:+.3f}], {self.trials} trials"

    def to_dict(self) -> dict:
        return {**asdict(self), "side": self.side}


def paired_map_difference(rows: Sequence[dict], a: str, b: str, metric: str, map_kind: str = "command",
                          seed: int = 0) -> MapDifference | None:
    """``a`` minus ``b`` over the trials (``seed`` column) where both have a finite ``metric`` for ``map_kind``."""
    if a == b:
        raise VitflyError(f"paired maps: compare two different models, got {a!r} twice")
    values: dict[str, dict[int, float]] = {a: {}, b: {}}
    for r in rows:
        v = r.get(metric)
        if r["model"] in values and r["map"] == map_kind and isinstance(v, int | float) and math.isfinite(v):
            values[r["model"]][int(r["seed"])] = float(v)
    seeds = sorted(values[a].keys() & values[b].keys())
    if not seeds:
        return None
    va = np.array([values[a][s] for s in seeds])
    vb = np.array([values[b][s] for s in seeds])
    low, high = scene_bootstrap_interval(np.array(seeds, dtype=np.int64), va - vb, seed=seed)
    return MapDifference(metric, map_kind, a, b, len(seeds), float(va.mean()), float(vb.mean()),
                         float((va - vb).mean()), low, high)


def map_finding(rows: Sequence[dict], a: str, b: str, map_kind: str = "command",
                metrics: Sequence[str] = STUDY_METRICS) -> dict:
    """The claims "a's maps higher than b's" on each of ``metrics`` (same map kind for both), and the verdict."""
    diffs = [d for m in metrics if (d := paired_map_difference(rows, a, b, m, map_kind)) is not None]
    verdict, why = claims_verdict([d.side for d in diffs])
    return {"a": a, "b": b, "map": map_kind, "comparisons": [d.to_dict() for d in diffs], "verdict": verdict,
            "why": why}


def run_study(
    policies: Sequence[ExplainedPolicy],
    trials: Sequence[tuple[int, Callable[[], TrialFrames]]],
    device: str = "cpu",
    progress: Callable[[str], None] | None = None,
) -> list[dict]:
    """Rows of every trial: ``trials`` holds (scene seed, a function giving that trial's frames)."""
    rows: list[dict] = []
    for i, (seed, make_frames) in enumerate(trials):
        frames = make_frames()
        if progress:
            progress(f"trial {i + 1}/{len(trials)}: seed {seed}, {len(frames)} ticks")
        rows += trial_rows(seed, frames, policies, device)
    return rows
