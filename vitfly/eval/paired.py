"""Paired comparisons of two policies flown on the same scenes.

Every policy of a sweep flies trial ``k`` of an env in the scene of seed ``derive_scene_seed(seed, env, k)``,
at every speed (``vitfly.eval.sweep``). So two policies are compared on pairs: the difference of a metric
between them, scene by scene, cancels the scene's own difficulty, which unpaired rates with their separate
intervals cannot. This module gives that difference with a 95 % interval.

Intervals. Success (0/1) at one speed: the exact interval that goes with McNemar's test. Only the discordant
pairs (one policy succeeded, the other not) carry the difference: given their number m, the count where ``a``
alone succeeded is binomial with p = 1/2 when neither policy is better, so the Clopper-Pearson interval of that
share, scaled to the difference (2 p - 1) m / n, excludes 0 exactly when McNemar's exact test rejects at 5 %
(``mcnemar_p``, given beside it). Everything else (collisions per trial, energy cost, commanded acceleration,
and success pooled over speeds): a paired bootstrap over scenes (``scipy.stats.bootstrap``, BCa, 10,000
resamples, seeded). A resample draws scenes with replacement and keeps every speed flown in each drawn scene
with both of its policies' trials, so the interval respects both the pairing and the scenes shared across speeds
(which McNemar's test, assuming independent pairs, would not); one method serves skewed counts and continuous
metrics alike, with no normal approximation.

Training draws. A model trained again with another seed flies differently (the laptop study's ConvNet: 21-59 %
pooled success over five seeds), so one training per model ranks trainings, not architectures. Where a policy
has several draws (``draws``: policy -> the labels of its draws), the difference is between the draws' means,
and its interval comes from a two-level bootstrap: each resample draws each policy's training draws with
replacement (independently: draws of two models are not paired), then the scenes with replacement (shared by
both policies: the pairing holds), percentile interval (BCa's jackknife has no two-level form). Resampling n
draws narrows the spread of their mean by (n - 1) / n, which matters at the 2-5 draws a study can afford, so
each policy's draws are first moved away from their mean by sqrt(n / (n - 1)) (``spread_draws``; a success
interval is then clipped to [-1, 1]). ``scripts/paired_calibration.py`` measures how often intervals decide
between two networks that are equal in expectation. A policy with one draw adds no training noise to the
interval of its own; where the study has trained other runs several times, a run trained once borrows their
spread: ``draws`` then lists every trained run (one label where it was trained once), and the difference gets a
normal term with the draws' pooled variance (``pooled_draw_variance``: between the means of each run's draws on
their shared trials, pooled over the runs with several, their degrees of freedom as weights), once for each side
trained once. Policies not in ``draws`` (the expert, straight flight, the planners) do not train and borrow
nothing.

A difference is *decided* when its interval excludes 0. ``verdict`` says which policy is better, or
``cannot tell``; the interval's half-width is the smallest difference the study could have told apart.
"""

from __future__ import annotations

import itertools
import math
import warnings
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, fields

import numpy as np
from scipy.stats import binomtest, bootstrap

from vitfly.errors import VitflyError
from vitfly.eval.aggregate import AGGREGATED_METRICS
from vitfly.eval.records import TrialRecord

# metric name -> (how to read it from a record, True when a higher value is better)
OUTCOMES = {"success": ("success_paper", True), "success_strict": ("success_strict", True)}
# speed_error: |actual forward speed / desired - 1|, how far a policy misses the speed asked of it
LOWER_IS_BETTER = ("collisions", "time_in_collision", "energy_cost", "cmd_acc", "lateral_dev_max", "speed_error")
METRICS = (*OUTCOMES, *LOWER_IS_BETTER, "speed_ratio")
HIGHER_IS_BETTER = {**{m: OUTCOMES[m][1] for m in OUTCOMES}, **{m: False for m in LOWER_IS_BETTER},
                    "speed_ratio": True}
RESAMPLES = 10_000
CONFIDENCE = 0.95


@dataclass(frozen=True)
class PairedDifference:
    """``a`` minus ``b`` on one metric over the (scene, speed) pairs both flew.

    ``diff`` is mean(a) - mean(b) over those pairs (for success: a fraction in [-1, 1]), ``low`` and
    ``high`` its 95 % interval (see the module docstring). For success at one speed, ``a_only`` / ``b_only``
    count the discordant pairs and ``mcnemar_p`` is McNemar's exact two-sided p-value.
    """

    metric: str
    a: str
    b: str
    env: str
    speeds: tuple[float, ...]
    pairs: int
    scenes: int
    mean_a: float
    mean_b: float
    diff: float
    low: float
    high: float
    a_only: int | None = None
    b_only: int | None = None
    mcnemar_p: float | None = None
    draws_a: int = 1  # training draws pooled into a (and b): the interval resamples them
    draws_b: int = 1
    borrowed_sd: float = 0.0  # pooled sd of one training draw, borrowed by each side trained once (0: none)

    @property
    def decided(self) -> bool:
        return self.low > 0 or self.high < 0

    @property
    def better(self) -> str | None:
        """The policy the interval shows better on this metric (None: cannot tell)."""
        if not self.decided:
            return None
        a_higher = self.low > 0
        return self.a if a_higher == HIGHER_IS_BETTER[self.metric] else self.b

    @property
    def side(self) -> str:
        """What this says of the claim "``a`` better than ``b``": "for", "against" or "undecided" (``claim_side``'s
        words; for a lower-is-better metric a difference below 0 is for)."""
        return {self.a: "for", self.b: "against"}.get(self.better, "undecided")

    @property
    def verdict(self) -> str:
        return f"{self.better} better" if self.better else "cannot tell"

    def text(self, digits: int = 2) -> str:
        """e.g. ``+12 points [+3, +21], 94 pairs, McNemar p=0.01`` (success in points)."""
        scale, unit = (100.0, " points") if self.metric in OUTCOMES else (1.0, "")
        d = 0 if self.metric in OUTCOMES else digits
        body = f"{scale * self.diff:+.{d}f}{unit} [{scale * self.low:+.{d}f}, {scale * self.high:+.{d}f}]"
        extra = f", McNemar p={self.mcnemar_p:.2g}" if self.mcnemar_p is not None else ""
        if self.draws_a > 1 or self.draws_b > 1 or self.borrowed_sd:
            extra += f", {self.draws_a} vs {self.draws_b} draws"
        if self.borrowed_sd:
            extra += f" (trained once: the pooled draw sd {scale * self.borrowed_sd:.{d}f}{unit} borrowed)"
        return f"{body}, {self.pairs} pairs{extra}"

    def to_dict(self) -> dict:
        return {**asdict(self), "verdict": self.verdict}

    @classmethod
    def from_dict(cls, d: Mapping, where: str = "paired difference") -> PairedDifference:
        """The inverse of ``to_dict`` (``verdict`` is recomputed), e.g. from a study's results.json."""
        names = [f.name for f in fields(cls)]
        try:
            return cls(**{**{k: d[k] for k in names if k in d}, "speeds": tuple(d["speeds"])})
        except (KeyError, TypeError) as err:
            raise VitflyError(f"{where}: not a paired difference ({type(err).__name__}: {err})") from None


def metric_value(rec: TrialRecord, metric: str) -> float:
    """One trial's value of ``metric`` (success as 0/1; nan when the trial leaves it undefined)."""
    if metric in OUTCOMES:
        return float(getattr(rec, OUTCOMES[metric][0]))
    if metric == "speed_error":
        return abs(metric_value(rec, "speed_ratio") - 1.0)
    if metric not in AGGREGATED_METRICS:
        raise VitflyError(f"paired metric {metric!r}: expected one of {', '.join(METRICS)}")
    value = rec.metrics.get(AGGREGATED_METRICS[metric][0])
    return math.nan if value is None else float(value)


def pairs(records: Iterable[TrialRecord], a: str, b: str, env: str, metric: str,
          speeds: Sequence[float] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Matched trials of ``a`` and ``b``: (scene seeds, speeds, a's values, b's values), one row per pair.

    A pair is one (scene seed, speed) that both flew in ``env``, with the metric defined for both.
    """
    scene, speed, va, vb = draw_pairs(records, [a], [b], env, metric, speeds)
    return scene, speed, va[0], vb[0]


def draw_pairs(records: Iterable[TrialRecord], a: Sequence[str], b: Sequence[str], env: str, metric: str,
               speeds: Sequence[float] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Matched trials of the draws ``a`` and ``b`` (labels): (scene seeds, speeds, values of a's draws (one row
    each), values of b's draws), one column per (scene seed, speed) that every draw flew with the metric defined."""
    wanted = None if speeds is None else {float(s) for s in speeds}
    labels = [*a, *b]
    values: dict[str, dict[tuple[int, float], float]] = {p: {} for p in labels}
    for rec in records:
        if rec.env == env and rec.policy in values and (wanted is None or float(rec.speed) in wanted):
            values[rec.policy][(rec.scene_seed, float(rec.speed))] = metric_value(rec, metric)
    shared = set.intersection(*(set(values[p]) for p in labels))
    keys = sorted(k for k in shared if all(math.isfinite(values[p][k]) for p in labels))
    rows = np.array([[values[p][k] for k in keys] for p in labels], dtype=np.float64).reshape(len(labels), len(keys))
    return (np.array([k[0] for k in keys], dtype=np.int64), np.array([k[1] for k in keys], dtype=np.float64),
            rows[: len(a)], rows[len(a):])


def spread_draws(sums: np.ndarray) -> np.ndarray:
    """Draws (rows) moved away from their mean by sqrt(n / (n - 1)), so that resampling n of them varies their mean
    as much as their unbiased variance says (plain resampling narrows it by (n - 1) / n); one draw is left as is."""
    n = len(sums)
    if n < 2:
        return sums
    mean = sums.mean(axis=0, keepdims=True)
    return mean + math.sqrt(n / (n - 1)) * (sums - mean)


def pooled_draw_variance(groups: Iterable[np.ndarray]) -> tuple[float, int] | None:
    """(variance, degrees of freedom) between training draws' means, pooled over runs: ``groups`` holds per run its
    draws' values (one row a draw) on the trials they all flew; a run with one draw adds nothing; None without
    a run of two or more."""
    squares, dof = 0.0, 0
    for values in groups:
        if len(values) > 1 and values.shape[1] > 0:
            means = values.mean(axis=1)
            squares += float(((means - means.mean()) ** 2).sum())
            dof += len(means) - 1
    return (squares / dof, dof) if dof else None


def two_level_bootstrap_interval(scene: np.ndarray, va: np.ndarray, vb: np.ndarray, confidence: float = CONFIDENCE,
                                 resamples: int = RESAMPLES, seed: int = 0, spread: bool = True,
                                 borrowed_var: float = 0.0) -> tuple[float, float]:
    """Percentile interval of mean(a's draws) - mean(b's draws) per pair, resampling each policy's draws (rows of
    ``va``, ``vb``, spread by ``spread_draws`` unless ``spread`` is False) and the scenes (columns grouped by
    ``scene``; all pairs of a drawn scene kept). ``borrowed_var``: the variance of a normal term added to every
    resample (the training noise of sides trained once, ``pooled_draw_variance``)."""
    ids, column_scene = np.unique(scene, return_inverse=True)
    counts = np.bincount(column_scene, minlength=len(ids)).astype(np.float64)
    # per draw and scene: the sum of its pairs' values
    sum_a = np.stack([np.bincount(column_scene, weights=row, minlength=len(ids)) for row in va])
    sum_b = np.stack([np.bincount(column_scene, weights=row, minlength=len(ids)) for row in vb])
    if spread:
        sum_a, sum_b = spread_draws(sum_a), spread_draws(sum_b)
    rng = np.random.default_rng(seed)
    stats = []
    for start in range(0, resamples, 2000):  # chunks: (chunk, scenes) arrays stay small
        n = min(2000, resamples - start)
        # times each draw (each scene) is drawn; integer weights keep 0/1 sums exact, so equal draws give exactly 0
        times_a = rng.multinomial(len(va), np.full(len(va), 1 / len(va)), size=n)
        times_b = rng.multinomial(len(vb), np.full(len(vb), 1 / len(vb)), size=n)
        times_s = rng.multinomial(len(ids), np.full(len(ids), 1 / len(ids)), size=n)
        per_scene = len(vb) * (times_a @ sum_a) - len(va) * (times_b @ sum_b)
        stat = (per_scene * times_s).sum(axis=1) / (len(va) * len(vb) * (times_s @ counts))
        stats.append(stat + rng.normal(0.0, math.sqrt(borrowed_var), n) if borrowed_var > 0 else stat)
    low, high = np.quantile(np.concatenate(stats), [(1 - confidence) / 2, (1 + confidence) / 2])
    return float(low), float(high)


def scene_bootstrap_interval(scene: np.ndarray, diff: np.ndarray, confidence: float = CONFIDENCE,
                             resamples: int = RESAMPLES, seed: int = 0) -> tuple[float, float]:
    """Bootstrap interval of mean(diff) resampling whole scenes (all pairs of a drawn scene kept).

    Per scene the sum of its differences and its pair count are resampled together (``paired=True``); the
    statistic is their ratio, the mean difference per pair. BCa; where BCa is undefined (e.g. every scene
    alike) the percentile interval, and a constant difference gives the point itself.
    """
    groups: dict[int, list[float]] = defaultdict(list)
    for s, d in zip(scene.tolist(), diff.tolist(), strict=True):
        groups[s].append(d)
    sums = np.array([sum(v) for v in groups.values()])
    counts = np.array([len(v) for v in groups.values()], dtype=np.float64)
    point = float(sums.sum() / counts.sum())
    if len(sums) < 2 or np.ptp(sums / counts) == 0:  # every resample gives the same ratio
        return point, point

    def ratio(s, n, axis=-1):
        return s.sum(axis=axis) / n.sum(axis=axis)

    for method in ("BCa", "percentile"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # BCa's degenerate-data warning: the percentile fallback follows
            ci = bootstrap((sums, counts), ratio, paired=True, vectorized=True, n_resamples=resamples,
                           confidence_level=confidence, method=method, rng=np.random.default_rng(seed)
                           ).confidence_interval
        if math.isfinite(ci.low) and math.isfinite(ci.high):
            return float(ci.low), float(ci.high)
    return point, point


def claim_side(low: float, high: float) -> str:
    """Where the 95 % interval [low, high] of A - B puts a claim that A is higher: "for" (wholly above 0),
    "against" (wholly below 0) or "undecided" (it holds 0)."""
    if not (math.isfinite(low) and math.isfinite(high)):
        return "undecided"
    return "for" if low > 0 else "against" if high < 0 else "undecided"


def claims_verdict(sides: Sequence[str]) -> tuple[str, str]:
    """(verdict, why) of a finding made of claims decided by ``claim_side``: every claim for "reproduced", any
    against "not", some for and none against "partly", none decided "cannot tell" (no claims: "n/a")."""
    won, lost = sum(s == "for" for s in sides), sum(s == "against" for s in sides)
    if not sides:
        return "n/a", "no claims"
    verdict = "not" if lost else ("reproduced" if won == len(sides) else "partly" if won else "cannot tell")
    return verdict, f"{won} of {len(sides)} claims decided for, {lost} against"


def mcnemar_exact(a_only: int, b_only: int) -> float:
    """McNemar's exact two-sided p-value: discordant pairs as a binomial with p = 1/2 (1.0 with none)."""
    n = a_only + b_only
    return 1.0 if n == 0 else float(binomtest(min(a_only, b_only), n, 0.5).pvalue)


def mcnemar_interval(a_only: int, b_only: int, pairs: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Exact interval of the success difference from the discordant pairs (see the module docstring)."""
    m = a_only + b_only
    if m == 0:
        return 0.0, 0.0
    ci = binomtest(a_only, m, 0.5).proportion_ci(confidence_level=confidence, method="exact")
    return (2 * ci.low - 1) * m / pairs, (2 * ci.high - 1) * m / pairs


def paired_difference(records: Iterable[TrialRecord], a: str, b: str, env: str, metric: str = "success",
                      speeds: Sequence[float] | None = None, confidence: float = CONFIDENCE,
                      resamples: int = RESAMPLES, seed: int = 0,
                      draws: Mapping[str, Sequence[str]] | None = None) -> PairedDifference | None:
    """``a`` minus ``b`` on ``metric`` in ``env`` (over ``speeds``, default all both flew); None without pairs.

    ``draws``: policy -> the labels of its training draws (its own label among them); a policy with several flown
    in ``env`` is compared by their mean, with the two-level interval of the module docstring. A policy listed
    with one flown draw borrows the pooled spread of the listed policies with several (none: nothing borrowed)."""
    if metric not in HIGHER_IS_BETTER:
        raise VitflyError(f"paired metric {metric!r}: expected one of {', '.join(METRICS)}")
    if draws and any(len(v) > 1 for v in draws.values()) and (a in draws or b in draws):
        records = list(records)
        flown = {rec.policy for rec in records if rec.env == env}  # a draw not flown (yet) is left out of its group
        draws_a = [p for p in draws.get(a) or [a] if p in flown] or [a]
        draws_b = [p for p in draws.get(b) or [b] if p in flown] or [b]
        trained_once = (a in draws and len(draws_a) == 1) + (b in draws and len(draws_b) == 1)
        pooled = _pooled(records, draws, flown, env, metric, speeds) if trained_once else None
        if len(draws_a) > 1 or len(draws_b) > 1 or pooled:
            return _draws_difference(records, a, b, draws_a, draws_b, env, metric, speeds, confidence, resamples,
                                     seed, pooled[0] if pooled else 0.0, trained_once)
    scene, speed, va, vb = pairs(records, a, b, env, metric, speeds)
    if len(va) == 0:
        return None
    a_only = b_only = p = None
    if metric in OUTCOMES:
        a_only, b_only = int(np.sum((va == 1) & (vb == 0))), int(np.sum((va == 0) & (vb == 1)))
    one_per_scene = len(set(scene.tolist())) == len(scene)  # one speed: the pairs are independent
    if metric in OUTCOMES and one_per_scene:
        p = mcnemar_exact(a_only, b_only)
        low, high = mcnemar_interval(a_only, b_only, len(va), confidence)
    else:
        low, high = scene_bootstrap_interval(scene, va - vb, confidence, resamples, seed)
    return PairedDifference(metric, a, b, env, tuple(sorted(set(speed.tolist()))), len(va), len(set(scene.tolist())),
                            float(va.mean()), float(vb.mean()), float((va - vb).mean()), low, high,
                            a_only, b_only, p)


def _pooled(records: list[TrialRecord], draws: Mapping[str, Sequence[str]], flown: set[str], env: str, metric: str,
            speeds: Sequence[float] | None) -> tuple[float, int] | None:
    """``pooled_draw_variance`` of the runs with two or more draws flown in ``env``."""
    groups = [[p for p in labels if p in flown] for labels in draws.values()]
    return pooled_draw_variance(draw_pairs(records, g, [], env, metric, speeds)[2] for g in groups if len(g) > 1)


def _draws_difference(records: Iterable[TrialRecord], a: str, b: str, draws_a: list[str], draws_b: list[str],
                      env: str, metric: str, speeds: Sequence[float] | None, confidence: float, resamples: int,
                      seed: int, draw_var: float = 0.0, trained_once: int = 0) -> PairedDifference | None:
    scene, speed, va, vb = draw_pairs(records, draws_a, draws_b, env, metric, speeds)
    if va.shape[1] == 0:
        return None
    diff = float(va.mean() - vb.mean())
    low, high = two_level_bootstrap_interval(scene, va, vb, confidence, resamples, seed,
                                             borrowed_var=trained_once * draw_var)
    if metric in OUTCOMES:  # spread draws can reach past what a success difference can be
        low, high = max(low, -1.0), min(high, 1.0)
    return PairedDifference(metric, a, b, env, tuple(sorted(set(speed.tolist()))), va.shape[1],
                            len(set(scene.tolist())), float(va.mean()), float(vb.mean()), diff, low, high,
                            draws_a=len(draws_a), draws_b=len(draws_b),
                            borrowed_sd=math.sqrt(draw_var) if trained_once else 0.0)


PAIRED_CSV_METRICS = ("success", "collisions")
PAIRED_CSV_COLUMNS = ("env", "metric", "a", "b", "speed", "pairs", "scenes", "mean_a", "mean_b", "diff", "low", "high",
                      "mcnemar_p", "verdict")


def paired_rows(records: Sequence[TrialRecord], metrics: Sequence[str] = PAIRED_CSV_METRICS) -> list[dict]:
    """Every pair of policies in every env, on each metric, per speed and over all speeds (``speed`` "all")."""
    rows = []
    for env in sorted({r.env for r in records}):
        in_env = [r for r in records if r.env == env]
        policies = sorted({r.policy for r in in_env})
        speeds = sorted({float(r.speed) for r in in_env})
        for metric in metrics:
            for a, b in itertools.combinations(policies, 2):
                for sp in [[s] for s in speeds] + ([None] if len(speeds) > 1 else []):
                    d = paired_difference(in_env, a, b, env, metric, sp)
                    if d is not None:
                        row = {k: v for k, v in d.to_dict().items() if k in PAIRED_CSV_COLUMNS}
                        rows.append({**row, "speed": "all" if sp is None else f"{sp[0]:g}"})
    return rows


def paired_csv(rows: Sequence[dict]) -> str:
    """``paired.csv`` text: one row per (env, metric, a, b, speed); a - b with its 95 % paired interval."""
    lines = [",".join(PAIRED_CSV_COLUMNS)]
    for r in rows:
        lines.append(",".join("" if r.get(c) is None else (f"{r[c]:.6g}" if isinstance(r[c], float) else str(r[c]))
                              for c in PAIRED_CSV_COLUMNS))
    return "\n".join(lines) + "\n"
