"""The paper's comparison with modular baselines, from the trial records of one sweep in which the modular planners
(``modular:NAME``, ``vitfly.planners``), ViT+LSTM and the expert flew the same spheres scenes at 1-7 m/s.

- ``replan_latency``: per planner, the measured compute time of every replan its trials record
  (``extra.replan_ms``): count, mean, 95th percentile and maximum, pooled over all its trials;
- ``cruise_speeds``: per policy and desired speed, the forward speed held between x = 10 m and x = 50 m (the
  distance over the time between the two crossings), past the take-off ramp and the acceleration from hover that
  the whole-trial mean forward speed includes (at 7 m/s they alone cost that mean ~10 %);
- ``velocity_matching``: the issue's velocity-matching target: ViT+LSTM's cruise speed within 10 % of the
  desired speed at every speed, and each design-speed (unscaled) planner's cruise speed saturating near its
  design speed (never above it by more than 10 %, whatever is asked);
- ``modular_markdown``: both as tables, with collisions and speeds per policy and speed.

The figure is ``vitfly.eval.paper_figures.modular_baselines_figure``; the finding decided on pairs is
``vitfly.eval.paired_findings.modular_baselines``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np

from vitfly.eval.metrics import crossing_time_s
from vitfly.eval.records import TrialRecord

CRUISE_WINDOW_M = (10.0, 50.0)  # world x (m): past the 2 m ramp and the acceleration, short of the 60 m goal
SPEED_TOLERANCE = 0.10  # the target: within 10 % of the desired (or design) speed
LEARNED_POLICY = "vit_lstm"


def planner_policies(recs: Sequence[TrialRecord]) -> dict[str, dict]:
    """Planner label -> {"design_speed_mps", "scaled"}: the policies whose records say they are modular planners."""
    out: dict[str, dict] = {}
    for r in recs:
        if str(r.extra.get("policy_source", "")).startswith("modular:") and r.policy not in out:
            out[r.policy] = {"design_speed_mps": r.extra.get("design_speed_mps"), "scaled": r.extra.get("scaled")}
    return dict(sorted(out.items()))


def replan_latency(recs: Sequence[TrialRecord]) -> dict[str, dict]:
    """Planner label -> {"trials", "replans", "mean_ms", "p95_ms", "max_ms"} over every replan of its trials."""
    times: dict[str, list[float]] = {}
    trials: dict[str, int] = {}
    for r in recs:
        ms = r.extra.get("replan_ms")
        if ms is None:
            continue
        times.setdefault(r.policy, []).extend(float(m) for m in ms)
        trials[r.policy] = trials.get(r.policy, 0) + 1
    out = {}
    for policy, values in sorted(times.items()):
        v = np.asarray(values)
        out[policy] = {"trials": trials[policy], "replans": len(v),
                       "mean_ms": float(v.mean()) if len(v) else float("nan"),
                       "p95_ms": float(np.percentile(v, 95)) if len(v) else float("nan"),
                       "max_ms": float(v.max()) if len(v) else float("nan")}
    return out


def cruise_speed_mps(rec: TrialRecord, window_m: tuple[float, float] = CRUISE_WINDOW_M) -> float:
    """Forward speed (m/s) between the first crossings of x = window_m[0] and x = window_m[1]; nan if the trial
    never reached the second (a stalled or crashed flight has no cruise)."""
    if not rec.path.get("time"):
        return float("nan")
    t, x = np.asarray(rec.path["time"], dtype=np.float64), np.asarray(rec.path["position"], dtype=np.float64)[:, 0]
    t0, t1 = crossing_time_s(t, x, window_m[0]), crossing_time_s(t, x, window_m[1])
    return (window_m[1] - window_m[0]) / (t1 - t0) if np.isfinite(t1) and t1 > t0 else float("nan")


def cruise_speeds(recs: Sequence[TrialRecord], window_m: tuple[float, float] = CRUISE_WINDOW_M,
                  ) -> dict[tuple[str, float], float]:
    """(policy, desired speed) -> mean cruise speed (m/s) over its trials that reached x = window_m[1]."""
    values: dict[tuple[str, float], list[float]] = {}
    for r in recs:
        v = cruise_speed_mps(r, window_m)
        if np.isfinite(v):
            values.setdefault((r.policy, float(r.speed)), []).append(v)
    return {k: float(np.mean(v)) for k, v in sorted(values.items())}


@dataclass(frozen=True)
class SpeedTarget:
    """One policy's side of the velocity-matching target.

    ``kind``: "tracks" (ViT+LSTM: |mean forward speed / desired - 1| <= tolerance at every speed) or "saturates"
    (a design-speed planner: mean forward speed <= (1 + tolerance) x design speed at every speed); ``met`` None
    when it was not flown. ``speeds`` / ``forward_mps`` / ``ratio``: per desired speed, the mean over its trials.
    """

    policy: str
    kind: str
    target: str
    met: bool | None
    speeds: tuple[float, ...]
    forward_mps: tuple[float, ...]
    ratio: tuple[float, ...]

    def to_dict(self) -> dict:
        return asdict(self)


def _per_speed(rows: Sequence[dict], policy: str, cruise: dict[tuple[str, float], float] | None,
               ) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
    sel = sorted((r for r in rows if r["policy"] == policy), key=lambda r: r["speed"])
    speeds = tuple(float(r["speed"]) for r in sel)
    if cruise is None:
        forward = tuple(float(r["forward_speed_mean"]) for r in sel)
        return speeds, forward, tuple(float(r["speed_ratio_mean"]) for r in sel)
    forward = tuple(cruise.get((policy, s), float("nan")) for s in speeds)
    return speeds, forward, tuple(f / s for f, s in zip(forward, speeds, strict=True))


def velocity_matching(rows: Sequence[dict], planners: dict[str, dict], tolerance: float = SPEED_TOLERANCE,
                      cruise: dict[tuple[str, float], float] | None = None) -> list[SpeedTarget]:
    """The target for ViT+LSTM and for every unscaled planner at the desired speeds of the summary rows
    (``vitfly.eval.aggregate``): on ``cruise`` speeds (``cruise_speeds``) where given, else on the rows' whole-trial
    mean forward speed. A speed without a cruise (no trial reached x = 50 m) fails ViT+LSTM's target."""
    out = []
    speeds, forward, ratio = _per_speed(rows, LEARNED_POLICY, cruise)
    met = all(abs(q - 1.0) <= tolerance for q in ratio) if speeds else None
    measure = "cruise speed (x 10-50 m)" if cruise is not None else "forward speed"
    out.append(SpeedTarget(LEARNED_POLICY, "tracks", f"{measure} within {100 * tolerance:.0f} % of the desired "
                           "at every speed", met, speeds, forward, ratio))
    for name, info in planners.items():
        design = info.get("design_speed_mps")
        if info.get("scaled") or design is None:
            continue
        speeds, forward, ratio = _per_speed(rows, name, cruise)
        met = not any(v > (1.0 + tolerance) * design for v in forward) if speeds else None  # nan: never above
        out.append(SpeedTarget(name, "saturates", f"{measure} at most {design * (1 + tolerance):.2g} m/s (design "
                               f"{design:g} m/s + {100 * tolerance:.0f} %) whatever the desired speed", met, speeds,
                               forward, ratio))
    return out


def _fmt(v: float, digits: int = 2) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{v:.{digits}f}"


def modular_markdown(rows: Sequence[dict], recs: Sequence[TrialRecord]) -> str:
    """Per policy and desired speed: collision rate, forward speed, trials; then the velocity-matching target and
    each planner's replan compute time."""
    policies = sorted({r["policy"] for r in rows})
    speeds = sorted({float(r["speed"]) for r in rows})
    by = {(r["policy"], float(r["speed"])): r for r in rows}
    head = " | ".join(f"{s:g} m/s" for s in speeds)
    lines = ["Collision rate (trials with a collision) / mean forward speed (m/s) / trials, per desired speed:", "",
             f"| policy | {head} |", "|---|" + "---:|" * len(speeds)]
    for p in policies:
        cells = []
        for s in speeds:
            r = by.get((p, s))
            collided = None if r is None else 100 * (1 - r["success_paper_rate"])
            cells.append("-" if r is None else f"{collided:.0f} % / {_fmt(r['forward_speed_mean'])} / {r['trials']}")
        lines.append(f"| {p} | " + " | ".join(cells) + " |")
    planners = planner_policies(recs)
    lines += ["", f"Velocity matching (cruise speed, x {CRUISE_WINDOW_M[0]:g}-{CRUISE_WINDOW_M[1]:g} m, / desired "
              "speed per desired speed):", "", "| policy | target | ratio per speed | met |", "|---|---|---|---|"]
    for t in velocity_matching(rows, planners, cruise=cruise_speeds(recs)):
        ratios = ", ".join(f"{s:g}: {q:.2f}" for s, q in zip(t.speeds, t.ratio, strict=True)) or "-"
        met = {None: "not flown", True: "yes", False: "no"}[t.met]
        lines.append(f"| {t.policy} | {t.target} | {ratios} | {met} |")
    latency = replan_latency(recs)
    lines += ["", "Replan compute time (measured, every replan of every trial; charged in simulated time):", "",
              "| planner | design speed (m/s) | scaled | trials | replans | mean (ms) | p95 (ms) | max (ms) |",
              "|---|---:|---|---:|---:|---:|---:|---:|"]
    for p, v in latency.items():
        info = planners.get(p, {})
        lines.append(f"| {p} | {info.get('design_speed_mps', '-')} | {'yes' if info.get('scaled') else 'no'} | "
                     f"{v['trials']} | {v['replans']} | {_fmt(v['mean_ms'], 1)} | {_fmt(v['p95_ms'], 1)} | "
                     f"{_fmt(v['max_ms'], 1)} |")
    return "\n".join(lines) + "\n"
