"""The paper's findings decided on pairs: each claim as differences between two policies flown on the same
scenes, each difference with its paired 95 % interval (``vitfly.eval.paired``), and a verdict that rests on
those intervals.

A claim "A is better than B" is *for* when the interval of A - B lies wholly on A's better side, *against*
when it lies wholly on B's, else undecided. A finding with several such claims is:

- ``reproduced``: every claim decided for it;
- ``not``: at least one decided against it;
- ``partly``: some decided for, none against, the rest undecided;
- ``cannot tell``: none decided (the study cannot tell the policies apart at its trial counts);
- ``n/a``: the policies or speeds were not flown.

Two findings are claims of absence or of one special contrast and say their own rule (``beats_expert_above_5``
and ``resnet_vs_convnet``). The two findings that compare against the paper's own numbers or a repeated single
scene (trees success at 7 m/s, the most direct path) are not pairs of policies and stay in the unpaired table.

The last finding is the paper's comparison with modular baselines (``modular_baselines``): ViT+LSTM against
each modular planner flown on the same spheres scenes at 1-7 m/s, on success and on the speed error.

Inputs: trial records of each sweep (``spheres``, ``trees``, ``window``, ``ablation``, ``modular``) with the labels of
``vitfly.eval.findings``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from vitfly.errors import VitflyError
from vitfly.eval.findings import LEARNED, NOSTATE_SUFFIX, VIT_MODELS, label
from vitfly.eval.paired import PairedDifference, claims_verdict, paired_difference
from vitfly.eval.records import TrialRecord

NOT_FLOWN = "the policies were not flown on shared scenes"
Draws = Mapping[str, Sequence[str]] | None  # policy -> the labels of its training draws (vitfly.eval.paired)
PAIRED_VERDICTS = ("reproduced", "partly", "not", "cannot tell", "n/a")
METRIC_WORDS = {"success": "success", "success_strict": "strict success", "collisions": "collisions per trial",
                "time_in_collision": "time in collision (s)", "energy_cost": "energy cost (1/s²)",
                "cmd_acc": "commanded acceleration (1/s²)",
                "speed_error": "speed error abs(actual / desired - 1)"}


@dataclass
class PairedFinding:
    key: str
    claim: str
    metric: str
    rule: str
    verdict: str
    comparisons: list[PairedDifference] = field(default_factory=list)  # each: a claimed better than b
    why: str = ""

    def to_dict(self) -> dict:
        return {"key": self.key, "claim": self.claim, "metric": self.metric, "rule": self.rule,
                "verdict": self.verdict, "why": self.why, "comparisons": [c.to_dict() for c in self.comparisons]}

    @classmethod
    def from_dict(cls, d: Mapping, where: str = "paired finding") -> PairedFinding:
        """The inverse of ``to_dict``: a finding as a study's results.json keeps it (``paired_findings``)."""
        try:
            comparisons = [PairedDifference.from_dict(c, f"{where}, comparison {i}")
                           for i, c in enumerate(d["comparisons"])]
            return cls(d["key"], d["claim"], d["metric"], d["rule"], d["verdict"], comparisons, d.get("why", ""))
        except (KeyError, TypeError) as err:
            raise VitflyError(f"{where}: not a paired finding ({type(err).__name__}: {err})") from None


def _speeds_of(records: Sequence[TrialRecord], policy: str) -> list[float]:
    return sorted({float(r.speed) for r in records if r.policy == policy})


def _learned(records: Sequence[TrialRecord]) -> list[str]:
    present = {r.policy for r in records}
    return [m for m in LEARNED if m in present]


def _decide(diffs: list[PairedDifference]) -> tuple[str, str]:
    """(verdict, why) of claims that each diff's ``a`` is the better, by the module's rule."""
    return claims_verdict([d.side for d in diffs])


def _over(draws: Draws) -> str:
    several = any(len(v) > 1 for v in (draws or {}).values())
    return ("paired over scenes and training draws (a model by its draws' mean; one trained once borrows the "
            "pooled spread of the others' draws)" if several else "paired over scenes")


def _rule(scope: str, draws: Draws = None) -> str:
    return (f"{scope}, {_over(draws)}: each claim 'A better than B' decided when the 95 % interval of A - B "
            "excludes 0; all for reproduced, any against not, some for partly, none decided cannot tell")


def _claims(key: str, claim: str, metric: str, records: Sequence[TrialRecord], pairs: list[tuple[str, str]],
            env: str, speeds: Sequence[float] | None, scope: str, draws: Draws = None) -> PairedFinding:
    """A finding made of claims "a better than b" for each of ``pairs``, decided by the rule above."""
    rule = _rule(f"{METRIC_WORDS[metric]} in {env} ({scope})", draws)
    diffs = [d for a, b in pairs
             if (d := paired_difference(records, a, b, env, metric, speeds, draws=draws)) is not None]
    if not diffs:
        return PairedFinding(key, claim, metric, rule, "n/a", why=NOT_FLOWN)
    verdict, why = _decide(diffs)
    return PairedFinding(key, claim, metric, rule, verdict, diffs, why)


def lowest_collisions_fast(spheres: Sequence[TrialRecord], draws: Draws = None) -> PairedFinding:
    speeds = [s for s in (6.0, 7.0) if s in _speeds_of(spheres, "vit_lstm")]
    others = [m for m in _learned(spheres) if m != "vit_lstm"]
    return _claims("lowest_collisions_6_7", "ViT+LSTM has the fewest collisions in Spheres at 6 and 7 m/s",
                   "collisions", spheres, [("vit_lstm", m) for m in others] if speeds else [], "spheres", speeds,
                   "6 and 7 m/s pooled", draws)


def beats_expert_fast(spheres: Sequence[TrialRecord], draws: Draws = None) -> PairedFinding:
    key, claim = "beats_expert_above_5", "ViT+LSTM is the only model with fewer collisions than the expert past 5 m/s"
    rule = (f"collisions per trial in spheres above 5 m/s, {_over(draws)}: ViT+LSTM decided below the expert "
            "and no other learned model decided below it reproduced; ViT+LSTM and others too partly; ViT+LSTM "
            "decided above the expert not; else cannot tell")
    speeds = [s for s in _speeds_of(spheres, "expert") if s > 5.0]
    diffs = [d for m in _learned(spheres) if speeds and
             (d := paired_difference(spheres, m, "expert", "spheres", "collisions", speeds, draws=draws)) is not None]
    mine = next((d for d in diffs if d.a == "vit_lstm"), None)
    if mine is None:
        return PairedFinding(key, claim, "collisions", rule, "n/a", why="ViT+LSTM or the expert not flown above 5 m/s")
    others = [d.a for d in diffs if d.a != "vit_lstm" and d.better == d.a]
    if mine.better == "vit_lstm":
        verdict = "partly" if others else "reproduced"
    else:
        verdict = "not" if mine.better == "expert" else "cannot tell"
    mine_text = {None: "cannot tell", "vit_lstm": "below", "expert": "above"}[mine.better]
    why = (f"ViT+LSTM vs the expert: {mine_text}; other models decided below the expert: "
           f"{', '.join(label(m) for m in others) or 'none'}")
    return PairedFinding(key, claim, "collisions", rule, verdict, diffs, why)


def less_time_in_collision_than_expert(spheres: Sequence[TrialRecord], draws: Draws = None) -> PairedFinding:
    speeds = [s for s in (3.0, 7.0) if s in _speeds_of(spheres, "expert")]
    return _claims("time_in_collision", "Learned models spend far less time in collision per obstacle than the expert",
                   "time_in_collision", spheres, [(m, "expert") for m in _learned(spheres)] if speeds else [],
                   "spheres", speeds, "3 and 7 m/s pooled", draws)


def vit_best_in_trees(trees: Sequence[TrialRecord], draws: Draws = None) -> PairedFinding:
    learned = _learned(trees)
    pairs = [(v, m) for v in VIT_MODELS if v in learned for m in learned if m not in VIT_MODELS]
    return _claims("vit_best_trees", "The ViT models generalise best to the unseen Trees", "collisions", trees,
                   pairs, "trees", None, "all speeds pooled", draws)


def only_vit_through_window(window: Sequence[TrialRecord], draws: Draws = None) -> PairedFinding:
    learned = _learned(window)
    pairs = [(v, m) for v in VIT_MODELS if v in learned for m in learned if m not in VIT_MODELS]
    return _claims("window_only_vit", "Only the ViT models fly through the window (3 m/s)", "success_strict", window,
                   pairs, "window", [3.0], "3 m/s", draws)


def lowest_energy(spheres: Sequence[TrialRecord], draws: Draws = None) -> PairedFinding:
    others = [m for m in _learned(spheres) if m != "vit_lstm"]
    return _claims("lowest_energy", "ViT+LSTM has the lowest energy cost in Spheres at every speed (3-7 m/s)",
                   "energy_cost", spheres, [("vit_lstm", m) for m in others], "spheres", None, "all speeds pooled",
                   draws)


def recurrence_lowers_acceleration(spheres: Sequence[TrialRecord], trees: Sequence[TrialRecord],
                                   draws: Draws = None) -> PairedFinding:
    parts = [_claims("recurrence_acc", "", "cmd_acc", recs, [("vit_lstm", "vit")], env, None, "all speeds pooled",
                     draws)
             for env, recs in (("spheres", spheres), ("trees", trees))]
    return _merge("recurrence_acc", "Recurrence lowers ViT's commanded acceleration (ViT+LSTM below ViT)", "cmd_acc",
                  parts, "commanded acceleration in spheres and in trees (all speeds pooled)", draws)


def state_helps_vit_lstm(ablation: Sequence[TrialRecord], draws: Draws = None) -> PairedFinding:
    parts = [_claims("state_helps_vit_lstm", "", "success", ablation, [("vit_lstm", "vit_lstm" + NOSTATE_SUFFIX)],
                     env, None, "ablation speeds pooled", draws) for env in ("spheres", "trees")]
    return _merge("state_helps_vit_lstm", "The state input (speed, attitude) helps ViT+LSTM", "success", parts,
                  "success in the ablation's spheres and trees (its speeds pooled)", draws)


def resnet_no_better(spheres: Sequence[TrialRecord], draws: Draws = None) -> PairedFinding:
    key, claim = "resnet_vs_convnet", "ResNet-18 is no better than ConvNet"
    rule = (f"success in spheres (all speeds pooled), {_over(draws)}: ResNet-18 - ConvNet decided above 0 not; "
            "decided below 0 or undecided reproduced, with the largest lead the interval allows")
    d = paired_difference(spheres, "resnet18", "convnet", "spheres", "success", draws=draws)
    if d is None:
        return PairedFinding(key, claim, "success", rule, "n/a", why="ResNet-18 and ConvNet not flown on shared scenes")
    verdict = "not" if d.better == "resnet18" else "reproduced"
    why = f"ResNet-18 at most {100 * d.high:+.0f} points over ConvNet (95 % upper bound)"
    return PairedFinding(key, claim, "success", rule, verdict, [d], why)


def modular_baselines(modular: Sequence[TrialRecord], draws: Draws = None) -> PairedFinding:
    """ViT+LSTM against every modular planner (``modular:NAME`` in the records' policy source) flown on the same
    spheres scenes, all speeds pooled: two claims per planner, ViT+LSTM the better on the paper's success (no
    collision) and on the speed error |actual forward speed / desired - 1|."""
    key = "modular_baselines"
    claim = ("The end-to-end ViT+LSTM keeps its collision rate and matches the desired speed across 1-7 m/s; "
             "the modular methods do not")
    planners = sorted({r.policy for r in modular if str(r.extra.get("policy_source", "")).startswith("modular:")})
    pairs = [("vit_lstm", p) for p in planners]
    parts = [_claims(key, claim, metric, modular, pairs, "spheres", None, "all speeds pooled", draws)
             for metric in ("success", "speed_error")]
    return _merge(key, claim, "success", parts, "success and speed error in spheres against each modular planner "
                  "(all speeds pooled)", draws)


def _merge(key: str, claim: str, metric: str, parts: list[PairedFinding], scope: str,
           draws: Draws = None) -> PairedFinding:
    """One finding from the claims of several environments, decided by the same rule over all of them."""
    diffs = [d for p in parts for d in p.comparisons]
    if not diffs:
        return PairedFinding(key, claim, metric, _rule(scope, draws), "n/a", why=NOT_FLOWN)
    verdict, why = _decide(diffs)
    return PairedFinding(key, claim, metric, _rule(scope, draws), verdict, diffs, why)


def paired_findings(spheres: Sequence[TrialRecord] | None, trees: Sequence[TrialRecord] | None,
                    window: Sequence[TrialRecord] | None,
                    ablation: Sequence[TrialRecord] | None,
                    modular: Sequence[TrialRecord] | None = None, draws: Draws = None) -> list[PairedFinding]:
    """Every paired finding, in the order of the unpaired table (``vitfly.eval.findings.paper_findings``), then the
    comparison with the modular baselines (``modular``: the records of that sweep). ``draws``: run label -> the
    labels of its training draws; such a run is compared by its draws' mean (``vitfly.eval.paired``)."""
    s, t, w, a, d = spheres or [], trees or [], window or [], ablation or [], draws
    return [lowest_collisions_fast(s, d), beats_expert_fast(s, d), less_time_in_collision_than_expert(s, d),
            vit_best_in_trees(t, d), only_vit_through_window(w, d), lowest_energy(s, d),
            recurrence_lowers_acceleration(s, t, d), state_helps_vit_lstm(a, d), resnet_no_better(s, d),
            modular_baselines(modular or [], d)]


def _policy(name: str) -> str:
    return name if name in ("expert", "straight") else label(name)


def paired_findings_markdown(findings: Sequence[PairedFinding]) -> str:
    """The paired findings table: one line per claim (A - B, interval, pairs), then each verdict's rule."""
    lines = ["| finding | claim (A better than B) | metric | A - B [95 % interval], pairs | decided | verdict |",
             "|---|---|---|---|---|---|"]
    for f in findings:
        if not f.comparisons:
            lines.append(f"| {f.claim} | - | {METRIC_WORDS[f.metric]} | - | - | **{f.verdict}** ({f.why}) |")
        for i, d in enumerate(f.comparisons):
            head = f.claim if i == 0 else ""
            verdict = f"**{f.verdict}** ({f.why})" if i == 0 else ""
            decided = "cannot tell" if d.side == "undecided" else d.side
            lines.append(f"| {head} | {_policy(d.a)} vs {_policy(d.b)}, {d.env} | {METRIC_WORDS[d.metric]} | "
                         f"{d.text()} | {decided} | {verdict} |")
    counts = ", ".join(f"{sum(f.verdict == v for f in findings)} {v}" for v in PAIRED_VERDICTS)
    rules = [f"- {f.claim}: {f.rule}." for f in findings]
    return "\n".join([*lines, "", f"Verdicts: {counts}.", "", *rules, ""])


def lead_table(records: Sequence[TrialRecord], env: str, leader: str = "vit_lstm",
               metric: str = "success", draws: Draws = None) -> str:
    """``leader`` minus every other policy of ``env`` on ``metric``, per speed and pooled, with paired intervals
    (the learned models, the expert and straight flight, then any other policy, e.g. the modular planners).
    ``draws``: a run with several training draws is one row, by its draws' mean; its draws get no rows."""
    extra_draws = {q for run, labels in (draws or {}).items() for q in labels if q != run}
    present = sorted({r.policy for r in records} - extra_draws)
    known = (*LEARNED, "expert", "straight")
    policies = [p for p in (*known, *(q for q in present if q not in known)) if p != leader and p in present]
    speeds = _speeds_of(records, leader)
    if not policies or not speeds:
        return "(not flown)\n"
    head = " | ".join(f"{s:g} m/s" for s in speeds)
    pooled = len(speeds) > 1
    lines = [f"| {_policy(leader)} minus | {head} |{' all speeds |' if pooled else ''}",
             "|---|" + "---:|" * (len(speeds) + pooled)]
    for p in policies:
        cells = []
        for sp in [[s] for s in speeds] + ([None] if len(speeds) > 1 else []):
            d = paired_difference(records, leader, p, env, metric, sp, draws=draws)
            cells.append("-" if d is None else f"{d.text()}{' *' if d.decided else ''}")
        lines.append(f"| {_policy(p)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
