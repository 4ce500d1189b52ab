"""Trial records -> one summary row per (policy, env, speed): rates, and mean and std of each metric."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable

import numpy as np

from vitfly.eval.metrics import spread
from vitfly.eval.records import TrialRecord

# rate column -> (outcome field of a record, description); success_paper_rate is the headline
RATE_COLUMNS: dict[str, tuple[str, str]] = {
    "success_paper_rate": ("success_paper", "success as the paper defines it: trials without a collision"),
    "success_strict_rate": ("success_strict", "vitfly's stricter success: goal reached and no collision"),
    "reached_goal_rate": ("reached_goal", "trials that reached x = goal"),
}

# summary column stem -> (metric key in a record, unit, description)
AGGREGATED_METRICS: dict[str, tuple[str, str, str]] = {
    "collisions": ("collisions", "", "collision entries per trial"),
    "time_in_collision": ("time_in_collision_s", "s",
                          "time in contact per collision, 0 for trials without one, mean over all trials (paper)"),
    "time_in_collision_colliding": ("time_in_collision_colliding_s", "s",
                                    "time in contact per collision, mean over trials with a collision only"),
    "energy_cost": ("energy_cost", "1/s^2", "sum |delta a| per metre travelled past x0 + 0.1 m (paper code)"),
    "energy_cost_optimal": ("energy_cost_optimal", "1/s^2", "sum |delta a| per metre of start-goal line"),
    "cmd_acc": ("cmd_acc", "1/s^2",
                "commands smoothed by np.convolve(ones(4)/4, 'same'), sum |dc/dt| per metre travelled (paper code)"),
    "lateral_dev_max": ("lateral_dev_max_m", "m", "largest |y - y0|"),
    "lateral_dev_mean": ("lateral_dev_mean_m", "m", "mean |y - y0|"),
    "forward_speed": ("forward_speed_mps", "m/s", "mean forward speed"),
    "speed_ratio": ("speed_ratio", "", "forward speed / desired speed"),
    "time_to_goal": ("time_to_goal_s", "s", "from crossing x0 + 0.5 m to crossing x = goal (trials that did)"),
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

    Each row: policy, policy_id (the hash of what was flown under that label), env, speed (m/s),
    trials, the fractions in [0, 1] of ``RATE_COLUMNS`` and ``<stem>_mean``, ``<stem>_std`` for
    every stem in ``AGGREGATED_METRICS`` (std over trials, ddof=1; undefined trial values skipped;
    nan when no trial defines it).
    """
    rows = []
    for (policy, env, speed), recs in group_records(records).items():
        ids = sorted({r.setup.get("policy_id", "") for r in recs})
        row: dict = {"policy": policy, "policy_id": ",".join(ids), "env": env, "speed": speed, "trials": len(recs)}
        for column, (attr, _) in RATE_COLUMNS.items():
            row[column] = float(np.mean([getattr(r, attr) for r in recs]))
        for stem, (key, _, _) in AGGREGATED_METRICS.items():
            s = spread(r.metrics.get(key) for r in recs)
            row[f"{stem}_mean"], row[f"{stem}_std"] = s.mean, s.std
        rows.append(row)
    return rows
