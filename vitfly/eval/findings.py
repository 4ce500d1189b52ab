"""The paper's findings, each checked against vitfly's evaluation: the paper's statement, our numbers with
trial counts and 95 % intervals, and a verdict by a stated rule.

Inputs are summary rows (``vitfly.eval.aggregate.summarize``) of the reproduce study's sweeps: ``spheres``
and ``trees`` (3-7 m/s, learned models with the state input, expert, straight), ``window`` (3 m/s) and
``ablation`` (models with and without the state input). Policy labels are registry names, ``<name>-nostate``
for the no-state runs, ``expert`` and ``straight``; another training draw of a run (another seed) is the run's
label and ``-s<seed>`` (``draw_label``). These findings read each run's own draw, the unsuffixed label.

Intervals: success rates get the 95 % Wilson score interval (``scipy.stats.binomtest``); means (collisions
per trial, energy, acceleration) get mean +- 1.96 standard errors (normal approximation).

Verdicts: ``reproduced``, ``partly``, ``not`` or ``n/a`` (a model or speed the study did not run); each
finding says its rule in ``rule`` and the comparison that decided in ``why``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import asdict, dataclass

from scipy.stats import binomtest

from vitfly.eval.paper_tables import MODEL_LABELS, paper_success

LEARNED = ("convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm", "resnet18")
VIT_MODELS = ("vit", "vit_lstm")
NOSTATE_SUFFIX = "-nostate"
STATE_SUFFIX = "-state"  # run folders with the state input (vitfly.workflows.reproduce_config), e.g. convnet-state
DRAW_PATTERN = re.compile(r"^(?P<run>.+)-s(?P<seed>\d+)$")  # convnet-s1, vit_lstm-nostate-s2
PAPER_TREES_7MPS_SUCCESS = {"vit": 80, "vit_lstm": 70}  # paper, supplementary: Trees success at 7 m/s (%)
# paper, results text: time in collision per obstacle in Spheres (s) at 3 and 7 m/s
PAPER_EXPERT_TIME_IN_COLLISION_S = {3.0: 1.20, 7.0: 0.45}
PAPER_WORST_LEARNED_TIME_IN_COLLISION_S = {3.0: 0.30, 7.0: 0.16}
PAPER_VIT_LSTM_MAX_LATERAL_M = 0.75  # paper: largest mean lateral deviation of ViT+LSTM in the fixed scene
VERDICTS = ("reproduced", "partly", "not", "n/a")


@dataclass
class Finding:
    key: str
    claim: str  # the paper's finding
    paper: str  # the paper's numbers or where it shows them
    ours: str  # vitfly's numbers, with trial counts and 95 % intervals
    verdict: str  # one of VERDICTS
    why: str  # the comparison that decided
    rule: str  # how the verdict is decided

    def to_dict(self) -> dict:
        return asdict(self)


def wilson(successes: int, trials: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a success rate (fractions in [0, 1])."""
    if trials <= 0:
        return math.nan, math.nan
    ci = binomtest(int(successes), int(trials)).proportion_ci(confidence_level=confidence, method="wilson")
    return float(ci.low), float(ci.high)


def draw_label(run: str, seed: int) -> str:
    """The policy label of another training draw of ``run`` (a label such as ``convnet-nostate``), with ``seed``."""
    return f"{run}-s{int(seed)}"


def split_draw(policy: str) -> tuple[str, int | None]:
    """(run label, seed) of a draw's label; (``policy``, None) for any other label."""
    m = DRAW_PATTERN.match(policy)
    return (m["run"], int(m["seed"])) if m else (policy, None)


def label(model: str) -> str:
    """A policy label for people: ConvNet, ViT+LSTM (no state), ConvNet, seed 3. A run folder's name with the state
    (``convnet-state``, as the paper-budget runs are named) reads as its model's."""
    run, seed = split_draw(model)
    base = run[: -len(NOSTATE_SUFFIX)] if run.endswith(NOSTATE_SUFFIX) else run
    if base == run and run.endswith(STATE_SUFFIX) and run[: -len(STATE_SUFFIX)] in MODEL_LABELS:
        run = base = run[: -len(STATE_SUFFIX)]
    text = MODEL_LABELS.get(base, base) + (" (no state)" if base != run else "")
    return text if seed is None else f"{text}, seed {seed}"


class Table:
    """Summary rows of one sweep, looked up by (policy, speed)."""

    def __init__(self, rows: Sequence[dict] | None):
        self.rows = {(r["policy"], float(r["speed"])): r for r in rows or []}

    def get(self, policy: str, speed: float) -> dict | None:
        return self.rows.get((policy, float(speed)))

    def policies(self) -> set[str]:
        return {p for p, _ in self.rows}

    def speeds(self, policy: str | None = None) -> list[float]:
        return sorted({s for p, s in self.rows if policy is None or p == policy})

    def learned(self) -> list[str]:
        return [m for m in LEARNED if m in self.policies()]

    def rate(self, policy: str, speed: float, column: str = "success_paper_rate") -> tuple[int, int] | None:
        """(successes, trials) of a rate column."""
        r = self.get(policy, speed)
        return None if r is None else (int(round(r[column] * r["trials"])), int(r["trials"]))

    def mean(self, policy: str, speed: float, stem: str) -> float | None:
        r = self.get(policy, speed)
        return None if r is None or not math.isfinite(r[f"{stem}_mean"]) else float(r[f"{stem}_mean"])

    def mean_text(self, policy: str, speed: float, stem: str, digits: int = 2) -> str:
        r = self.get(policy, speed)
        if r is None or not math.isfinite(r[f"{stem}_mean"]):
            return "-"
        mean, std, n = r[f"{stem}_mean"], r[f"{stem}_std"], r["trials"]
        half = 1.96 * std / math.sqrt(n) if n > 1 and math.isfinite(std) else math.nan
        ci = f" [{mean - half:.{digits}f}, {mean + half:.{digits}f}]" if math.isfinite(half) else ""
        return f"{mean:.{digits}f}{ci}"

    def pooled(self, policy: str, column: str = "success_paper_rate") -> tuple[int, int]:
        """(successes, trials) of a rate column over all speeds."""
        k = n = 0
        for s in self.speeds(policy):
            kk, nn = self.rate(policy, s, column)
            k, n = k + kk, n + nn
        return k, n

    def pooled_mean(self, policy: str, stem: str) -> float:
        total = n = 0.0
        for s in self.speeds(policy):
            r = self.get(policy, s)
            if math.isfinite(r[f"{stem}_mean"]):
                total += r[f"{stem}_mean"] * r["trials"]
                n += r["trials"]
        return total / n if n else math.nan


def rate_text(k: int, n: int) -> str:
    lo, hi = wilson(k, n)
    return f"{100 * k / n:.0f} % ({k}/{n}, CI {100 * lo:.0f}-{100 * hi:.0f} %)" if n else "-"


def _share(hits: int, total: int) -> str:
    if total and hits == total:
        return "reproduced"
    return "partly" if hits > total / 2 else "not"


def _na(key: str, claim: str, paper: str, rule: str, why: str) -> Finding:
    return Finding(key, claim, paper, "-", "n/a", why, rule)


def lowest_collisions_fast(spheres: Table) -> Finding:
    key, claim = "lowest_collisions_6_7", "ViT+LSTM has the fewest collisions in Spheres at 6 and 7 m/s"
    paper = "figure (collision rate vs speed): ViT+LSTM lowest beyond 6 m/s"
    rule = ("collisions per trial of ViT+LSTM at or below every other learned model's: at both 6 and 7 m/s "
            "reproduced, at one partly, at neither not")
    speeds = [s for s in (6.0, 7.0) if spheres.get("vit_lstm", s)]
    others = [m for m in spheres.learned() if m != "vit_lstm"]
    if not speeds or not others:
        return _na(key, claim, paper, rule, "ViT+LSTM or another learned model not flown at 6-7 m/s")
    wins, parts, ours = 0, [], []
    for s in speeds:
        vals = {m: spheres.mean(m, s, "collisions") for m in others if spheres.mean(m, s, "collisions") is not None}
        mine = spheres.mean("vit_lstm", s, "collisions")
        best = min(vals, key=vals.get)
        wins += mine <= vals[best]
        n = spheres.get("vit_lstm", s)["trials"]
        ours.append(f"{s:g} m/s: ViT+LSTM {spheres.mean_text('vit_lstm', s, 'collisions')} (n={n})")
        parts.append(f"{s:g} m/s: ViT+LSTM {mine:.2f} vs best other {label(best)} {vals[best]:.2f}")
    verdict = "reproduced" if wins == len(speeds) == 2 else ("partly" if wins else "not")
    return Finding(key, claim, paper, "; ".join(ours), verdict, "; ".join(parts), rule)


def beats_expert_fast(spheres: Table) -> Finding:
    key, claim = "beats_expert_above_5", "ViT+LSTM is the only model with fewer collisions than the expert past 5 m/s"
    paper = "figure (collision rate vs speed): ViT+LSTM below the expert at 6 and 7 m/s, no other model"
    rule = ("fewer collisions per trial than the expert at every evaluated speed above 5 m/s: ViT+LSTM and no "
            "other learned model reproduced; ViT+LSTM at some of those speeds (or others too) partly; else not")
    speeds = [s for s in spheres.speeds("expert") if s > 5.0 and spheres.get("vit_lstm", s)]
    if not speeds:
        return _na(key, claim, paper, rule, "ViT+LSTM or the expert not flown above 5 m/s")
    beats = {m: [spheres.mean(m, s, "collisions") < spheres.mean("expert", s, "collisions")
                 for s in speeds if spheres.get(m, s)] for m in spheres.learned()}
    others = [m for m, b in beats.items() if m != "vit_lstm" and b and all(b)]
    mine = beats["vit_lstm"]
    verdict = "reproduced" if all(mine) and not others else ("partly" if any(mine) else "not")
    ours = "; ".join(f"{s:g} m/s: ViT+LSTM {spheres.mean_text('vit_lstm', s, 'collisions')}, expert "
                     f"{spheres.mean_text('expert', s, 'collisions')} (n={spheres.get('vit_lstm', s)['trials']})"
                     for s in speeds)
    why = (f"ViT+LSTM below the expert at {sum(mine)} of {len(speeds)} speeds above 5 m/s; other models below it "
           f"at all of them: {', '.join(label(m) for m in others) or 'none'}")
    return Finding(key, claim, paper, ours, verdict, why, rule)


def vit_best_in_trees(trees: Table) -> Finding:
    key, claim = "vit_best_trees", "The ViT models generalise best to the unseen Trees"
    paper = "figure (Trees collision rate): ViT and ViT+LSTM lowest"
    rule = ("learned models ranked by collisions per trial pooled over 3-7 m/s: ViT and ViT+LSTM the two "
            "lowest reproduced; one of them among the two lowest partly; else not")
    models = trees.learned()
    if len(models) < 3 or not any(m in models for m in VIT_MODELS):
        return _na(key, claim, paper, rule, "fewer than three learned models (or no ViT model) flown in Trees")
    pooled = {m: trees.pooled_mean(m, "collisions") for m in models}
    ranked = sorted(pooled, key=pooled.get)
    top = ranked[:2]
    hits = sum(m in top for m in VIT_MODELS)
    verdict = "reproduced" if hits == 2 else ("partly" if hits == 1 else "not")
    ours = ", ".join(f"{label(m)} {pooled[m]:.2f}" for m in ranked) + " collisions per trial (pooled)"
    return Finding(key, claim, paper, ours, verdict, f"two lowest: {', '.join(label(m) for m in top)}", rule)


def trees_success_at_7(trees: Table) -> Finding:
    key, claim = "trees_success_7", "ViT 80 % and ViT+LSTM 70 % success in Trees at 7 m/s"
    paper = "ViT 80 %, ViT+LSTM 70 % (10 trials each; supplementary)"
    rule = "the paper's rate inside our 95 % Wilson interval: for both models reproduced, for one partly, else not"
    present = [m for m in VIT_MODELS if trees.get(m, 7.0)]
    if not present:
        return _na(key, claim, paper, rule, "no ViT model flown in Trees at 7 m/s")
    inside, ours, why = 0, [], []
    for m in present:
        k, n = trees.rate(m, 7.0)
        lo, hi = wilson(k, n)
        ok = lo <= PAPER_TREES_7MPS_SUCCESS[m] / 100 <= hi
        inside += ok
        ours.append(f"{label(m)} {rate_text(k, n)}")
        why.append(f"{label(m)}: paper {PAPER_TREES_7MPS_SUCCESS[m]} % {'inside' if ok else 'outside'}")
    verdict = "reproduced" if inside == len(VIT_MODELS) else ("partly" if inside else "not")
    why += [f"{label(m)} not flown" for m in VIT_MODELS if m not in present]
    return Finding(key, claim, paper, "; ".join(ours), verdict, "; ".join(why), rule)


def only_vit_through_window(window: Table) -> Finding:
    key, claim = "window_only_vit", "Only the ViT models fly through the window (3 m/s)"
    paper = "figure (window paths): ViT and ViT+LSTM succeed, all others fail"
    rule = ("strict success (goal reached, no collision) at 3 m/s: every ViT model > 0 and every other learned "
            "model 0 reproduced; the best ViT model above every other model partly; else not")
    models = [m for m in window.learned() if window.get(m, 3.0)]
    vits = [m for m in models if m in VIT_MODELS]
    rest = [m for m in models if m not in VIT_MODELS]
    if not vits or not rest:
        return _na(key, claim, paper, rule, "ViT and non-ViT models are both needed in the window at 3 m/s")
    rates = {m: window.rate(m, 3.0, "success_strict_rate") for m in models}
    share = {m: k / n for m, (k, n) in rates.items()}
    if all(share[m] > 0 for m in vits) and all(share[m] == 0 for m in rest):
        verdict = "reproduced"
    else:
        verdict = "partly" if max(share[m] for m in vits) > max(share[m] for m in rest) else "not"
    ours = "; ".join(f"{label(m)} {rate_text(*rates[m])}" for m in models)
    why = (f"best ViT {max(share[m] for m in vits):.0%}, best other {max(share[m] for m in rest):.0%}; "
           f"others through: {', '.join(label(m) for m in rest if share[m] > 0) or 'none'}")
    return Finding(key, claim, paper, ours, verdict, why, rule)


def lowest_energy(spheres: Table) -> Finding:
    key, claim = "lowest_energy", "ViT+LSTM has the lowest energy cost in Spheres at every speed (3-7 m/s)"
    paper = "figure (energy cost vs speed): ViT+LSTM lowest of all models, nearly flat with speed"
    rule = ("energy cost of ViT+LSTM at or below every other learned model's: at every evaluated speed "
            "reproduced, at most of them partly, else not")
    speeds = spheres.speeds("vit_lstm")
    others = [m for m in spheres.learned() if m != "vit_lstm"]
    if not speeds or not others:
        return _na(key, claim, paper, rule, "ViT+LSTM or another learned model not flown in Spheres")
    wins, why = 0, []
    for s in speeds:
        vals = {m: spheres.mean(m, s, "energy_cost") for m in others if spheres.mean(m, s, "energy_cost") is not None}
        mine = spheres.mean("vit_lstm", s, "energy_cost")
        best = min(vals, key=vals.get) if vals else None
        if mine is not None and best is not None:
            wins += mine <= vals[best]
            why.append(f"{s:g}: {mine:.2f} vs {label(best)} {vals[best]:.2f}")
    ours = "; ".join(f"{s:g} m/s {spheres.mean_text('vit_lstm', s, 'energy_cost')}" for s in speeds)
    return Finding(key, claim, paper, f"ViT+LSTM {ours} 1/s² (n={spheres.get('vit_lstm', speeds[0])['trials']})",
                   _share(wins, len(speeds)), f"lowest at {wins} of {len(speeds)} speeds ({'; '.join(why)})", rule)


def recurrence_lowers_acceleration(spheres: Table, trees: Table) -> Finding:
    key, claim = "recurrence_acc", "Recurrence lowers ViT's commanded acceleration (ViT+LSTM below ViT)"
    paper = "figure (acceleration vs speed, Spheres and Trees): ViT+LSTM below ViT"
    rule = ("commanded acceleration of ViT+LSTM below ViT's in each (environment, speed): in all reproduced, "
            "in most partly, else not")
    cells = [(env, t, s) for env, t in (("spheres", spheres), ("trees", trees))
             for s in t.speeds("vit_lstm") if t.get("vit", s)]
    if not cells:
        return _na(key, claim, paper, rule, "ViT and ViT+LSTM not both flown")
    lower = [t.mean("vit_lstm", s, "cmd_acc") < t.mean("vit", s, "cmd_acc") for _, t, s in cells]
    ours = "; ".join(f"{env} {s:g} m/s: ViT+LSTM {t.mean_text('vit_lstm', s, 'cmd_acc', 1)} vs ViT "
                     f"{t.mean_text('vit', s, 'cmd_acc', 1)}" for env, t, s in cells)
    return Finding(key, claim, paper, ours, _share(sum(lower), len(cells)),
                   f"ViT+LSTM lower in {sum(lower)} of {len(cells)} cells", rule)


def state_helps_vit_lstm(ablation: dict[str, Table]) -> Finding:
    key, claim = "state_helps_vit_lstm", "The state input (speed, attitude) helps ViT+LSTM"
    cells = [(env, s) for env, t in ablation.items() for s in t.speeds("vit_lstm")
             if t.get("vit_lstm" + NOSTATE_SUFFIX, s)]
    paper_cells = [(env, s, paper_success(env, "vit_lstm", s, False), paper_success(env, "vit_lstm", s, True))
                   for env in ("spheres", "trees") for s in (3.0, 5.0, 7.0)]
    paper = "; ".join(f"{env} {s:g} m/s {a}→{b} %" for env, s, a, b in paper_cells) + " (without→with, 11 trials)"
    rule = ("success with the state at or above without it in every (environment, speed) cell and above in at "
            "least half reproduced; at or above in most cells partly; else not")
    if not cells:
        return _na(key, claim, paper, rule, "ViT+LSTM not trained and flown both with and without the state")
    ge = gt = 0
    ours = []
    for env, s in cells:
        t = ablation[env]
        k1, n1 = t.rate("vit_lstm", s)
        k0, n0 = t.rate("vit_lstm" + NOSTATE_SUFFIX, s)
        ge += k1 / n1 >= k0 / n0
        gt += k1 / n1 > k0 / n0
        ours.append(f"{env} {s:g} m/s {rate_text(k0, n0)} → {rate_text(k1, n1)}")
    if ge == len(cells) and gt >= len(cells) / 2:
        verdict = "reproduced"
    else:
        verdict = "partly" if ge > len(cells) / 2 else "not"
    return Finding(key, claim, paper, "; ".join(ours), verdict,
                   f"with ≥ without in {ge} of {len(cells)} cells, > in {gt}", rule)


def less_time_in_collision_than_expert(spheres: Table) -> Finding:
    key, claim = "time_in_collision", "Learned models spend far less time in collision per obstacle than the expert"
    expert, worst = PAPER_EXPERT_TIME_IN_COLLISION_S, PAPER_WORST_LEARNED_TIME_IN_COLLISION_S
    paper = (f"expert {expert[3.0]:.2f} s at 3 m/s, {expert[7.0]:.2f} s at 7 m/s; worst learned model "
             f"{worst[3.0]:.2f} s, {worst[7.0]:.2f} s")
    rule = ("time in collision per obstacle (0 for a trial without one, mean over all trials, as the paper "
            "plots it) of each learned model below the expert's at 3 and 7 m/s: in every (model, speed) cell "
            "reproduced, in most partly, else not")
    speeds = [s for s in (3.0, 7.0) if spheres.get("expert", s)]
    cells = [(m, s) for s in speeds for m in spheres.learned() if spheres.get(m, s)]
    if not cells:
        return _na(key, claim, paper, rule, "the expert and learned models not flown at 3 or 7 m/s")
    below = sum(spheres.mean(m, s, "time_in_collision") < spheres.mean("expert", s, "time_in_collision")
                for m, s in cells)
    ours = []
    for s in speeds:
        learned = {m: spheres.mean(m, s, "time_in_collision") for m, ss in cells if ss == s}
        if learned:
            worst = max(learned, key=learned.get)
            ours.append(f"{s:g} m/s: expert {spheres.mean_text('expert', s, 'time_in_collision')} s, worst learned "
                        f"{label(worst)} {spheres.mean_text(worst, s, 'time_in_collision')} s "
                        f"(n={spheres.get('expert', s)['trials']})")
    return Finding(key, claim, paper, "; ".join(ours), _share(below, len(cells)),
                   f"below the expert in {below} of {len(cells)} (model, speed) cells", rule)


def most_direct_path(lateral: dict[str, float] | None) -> Finding:
    key, claim = "most_direct_path", "ViT+LSTM takes the most direct path through a fixed Spheres scene"
    paper = f"figure (paths): ViT+LSTM's largest mean lateral deviation {PAPER_VIT_LSTM_MAX_LATERAL_M} m, the least"
    rule = ("largest |mean y - start y| over the repeats of one scene: ViT+LSTM's the smallest of the learned "
            "models reproduced, else not")
    learned = {m: v for m, v in (lateral or {}).items() if m in LEARNED and math.isfinite(v)}
    if "vit_lstm" not in learned or len(learned) < 2:
        return _na(key, claim, paper, rule, "ViT+LSTM and another learned model not flown in the fixed scene")
    ranked = sorted(learned, key=learned.get)
    verdict = "reproduced" if ranked[0] == "vit_lstm" else "not"
    ours = ", ".join(f"{label(m)} {learned[m]:.2f} m" for m in ranked)
    return Finding(key, claim, paper, ours, verdict, f"smallest: {label(ranked[0])}", rule)


def resnet_no_better(spheres: Table) -> Finding:
    key, claim = "resnet_vs_convnet", "ResNet-18 is no better than ConvNet"
    paper = "text: 'found to perform similarly to the ConvNet model' (no numbers)"
    rule = ("success in Spheres pooled over 3-7 m/s: ResNet-18 at or below ConvNet, or the two 95 % Wilson "
            "intervals overlapping, reproduced; ResNet-18's interval wholly above ConvNet's not")
    if not all(spheres.speeds(m) for m in ("resnet18", "convnet")):
        return _na(key, claim, paper, rule, "ResNet-18 and ConvNet not both flown in Spheres")
    r, c = spheres.pooled("resnet18"), spheres.pooled("convnet")
    (rlo, _), (_, chi) = wilson(*r), wilson(*c)
    better = rlo > chi
    verdict = "not" if better else "reproduced"
    why = f"ResNet-18 lower bound {100 * rlo:.0f} % {'>' if better else '<='} ConvNet upper bound {100 * chi:.0f} %"
    return Finding(key, claim, paper, f"ResNet-18 {rate_text(*r)}; ConvNet {rate_text(*c)}", verdict, why, rule)


def paper_findings(spheres: Sequence[dict] | None, trees: Sequence[dict] | None, window: Sequence[dict] | None,
                   ablation: Sequence[dict] | None, lateral: dict[str, float] | None = None) -> list[Finding]:
    """Every finding of the paper's results section, checked.

    Summary rows of each sweep (None: not run); ``lateral``: each policy's largest mean lateral deviation
    (m) over the repeats of one scene (``vitfly.eval.paper_figures.mean_paths``).
    """
    s, t, w = Table(spheres), Table(trees), Table(window)
    abl = {env: Table([r for r in ablation or [] if r["env"] == env]) for env in ("spheres", "trees")}
    return [lowest_collisions_fast(s), beats_expert_fast(s), less_time_in_collision_than_expert(s),
            most_direct_path(lateral), vit_best_in_trees(t), trees_success_at_7(t), only_vit_through_window(w),
            lowest_energy(s), recurrence_lowers_acceleration(s, t), state_helps_vit_lstm(abl), resnet_no_better(s)]


def findings_markdown(findings: Sequence[Finding]) -> str:
    """The findings table, then each verdict's rule."""
    def cell(text: str) -> str:
        return text.replace("|", "\\|")

    lines = ["| # | paper's finding | paper | vitfly (trials, 95 % interval) | verdict | why |",
             "|---:|---|---|---|---|---|"]
    for i, f in enumerate(findings, 1):
        lines.append(f"| {i} | {cell(f.claim)} | {cell(f.paper)} | {cell(f.ours)} | **{f.verdict}** | "
                     f"{cell(f.why)} |")
    rules = [f"{i}. {f.rule}." for i, f in enumerate(findings, 1)]
    counts = ", ".join(f"{sum(f.verdict == v for f in findings)} {v}" for v in VERDICTS)
    intervals = ("Intervals: 95 % Wilson score intervals for rates (success); mean ± 1.96 standard errors for means "
                 "(collisions per trial, time in collision, energy cost, commanded acceleration). n: trials per cell.")
    return "\n".join([*lines, "", f"Verdicts: {counts}.", "", intervals, "", "Rules (one per row):", "", *rules, ""])
