"""Trial records -> one summary row per (policy, env, speed): rates, and mean and std of each metric."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable

import numpy as np

from vitfly.eval.metrics import spread
from vitfly.eval.records import TrialRecord

# summary column stem -> (metric key in a record, unit, description)
AGGREGATED_METRICS: dict[str, tuple[str, str, str]] = {
    "collisions": ("collisions", "", "collision entries per trial"),
    "time_in_collision": ("time_in_collision_s", "s", "time in contact per collision (trials with one)"),
    "energy_cost": ("energy_cost", "1/s^2", "sum |delta a| per metre flown (paper code)"),
    "energy_cost_optimal": ("energy_cost_optimal", "1/s^2", "sum |delta a| per metre of start-goal line"),
    "cmd_acc": ("cmd_acc", "1/s^2", "commanded acceleration per metre flown"),
    "lateral_dev_max": ("lateral_dev_max_m", "m", "largest |y - y0|"),
    "lateral_dev_mean": ("lateral_dev_mean_m", "m", "mean |y - y0|"),
    "forward_speed": ("forward_speed_mps", "m/s", "mean forward speed"),
    "speed_ratio": ("speed_ratio", "", "forward speed / desired speed"),
    "time_to_goal": ("time_to_goal_s", "s", "time to reach x = goal (trials that did)"),
    "processing_ms": ("processing_ms", "ms", "policy time per control tick"),
}

GROUP_COLUMNS = ("policy", "env", "speed")


def group_records(records: Iterable[TrialRecord]) -> dict[tuple[str, str, float], list[TrialRecord]]:
    groups: dict[tuple[str, str, float], list[TrialRecord]] = defaultdict(list)
    for rec in records:
        groups[(rec.policy, rec.env, float(rec.speed))].append(rec)
    return dict(sorted(groups.items()))


def summarize(records: Iterable[TrialRecord]) -> list[dict]:
    """Summary rows sorted by (policy, env, speed).

    Each row: policy, env, speed (m/s), trials, success_rate, reached_goal_rate, collision_free_rate
    (fractions in [0, 1]) and ``<stem>_mean``, ``<stem>_std`` for every stem in ``AGGREGATED_METRICS``
    (std over trials, ddof=1; undefined trial values skipped; nan when no trial defines it).
    """
    rows = []
    for (policy, env, speed), recs in group_records(records).items():
        row: dict = {"policy": policy, "env": env, "speed": speed, "trials": len(recs)}
        row["success_rate"] = float(np.mean([r.success for r in recs]))
        row["reached_goal_rate"] = float(np.mean([r.reached_goal for r in recs]))
        row["collision_free_rate"] = float(np.mean([r.metrics.get("collisions", 0) == 0 for r in recs]))
        for stem, (key, _, _) in AGGREGATED_METRICS.items():
            s = spread(r.metrics.get(key) for r in recs)
            row[f"{stem}_mean"], row[f"{stem}_std"] = s.mean, s.std
        rows.append(row)
    return rows
