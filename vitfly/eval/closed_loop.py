"""The closed-loop numbers a weights manifest records (``closed_loop``): success and collisions per env and speed.

``vitfly reproduce`` writes them for the networks it trains and flies (``closed_loop_cells`` over the study's
summary rows); ``vitfly publish-weights --closed-loop-from DIR ...`` takes them from evaluation folders
(``closed_loop_from_sweeps``), and only from trials flown with the very weights being published: every trial
of the policy must carry the ``policy_id`` of that network (``vitfly.eval.fingerprint``), so that numbers
never travel with weights they do not belong to.

Example::

    numbers = closed_loop_from_sweeps(["runs/x/eval/spheres", "runs/x/eval/trees"], "convnet-s2", net)
    # {"eval_seed": 1000, "scene_preset": "medium", "success": "no collision", "physics": "pybullet",
    #  "backend": "eager", "spheres": {"3": {"success": 0.8, "success_strict": 0.8, ...}, ...}, ...}
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from vitfly.errors import VitflyError
from vitfly.eval import records
from vitfly.eval.aggregate import summarize
from vitfly.eval.fingerprint import learned_policy_id, network_fingerprint

STUDY_ENVS = ("spheres", "trees", "window")  # the paper's envs (not the hardware course)


def closed_loop_cells(rows: Sequence[dict], policy: str) -> dict:
    """env -> speed (as "3", "5") -> success (the paper's), strict success, collisions per trial and trials of
    ``policy``'s summary rows (``vitfly.eval.aggregate.summarize``) in the study's envs."""
    out: dict = {}
    for r in rows:
        if r["policy"] == policy and r["env"] in STUDY_ENVS:
            out.setdefault(r["env"], {})[f"{r['speed']:g}"] = {
                "success": r["success_paper_rate"], "success_strict": r["success_strict_rate"],
                "collisions_per_trial": r["collisions_mean"], "trials": r["trials"]}
    return out


def closed_loop_from_sweeps(dirs: Sequence[str | Path], policy: str, net) -> dict:
    """The manifest's ``closed_loop`` of ``net`` from the trials labelled ``policy`` in the evaluation folders
    ``dirs`` (their trial files, else their published outcomes file). One-line VitflyError when the folders
    hold no such trials, when any of them was flown with other weights, or when they mix seeds, scene
    presets, physics back ends or inference back ends (one manifest entry states one protocol)."""
    names = ", ".join(str(d) for d in dirs)
    found = []
    for d in dirs:
        if not Path(d).is_dir():
            raise VitflyError(f"{d}: no such evaluation folder (--closed-loop-from)")
        found += [r for r in records.read_report_records(d) if r.policy == policy]
    if not found:
        raise VitflyError(f"{names}: no trials of policy {policy!r} (--closed-loop-policy names the label the "
                          "weights were flown under)")
    weights = network_fingerprint(net)
    for rec in found:
        if rec.setup.get("policy_id") != learned_policy_id(weights, rec.extra.get("backend")):
            raise VitflyError(f"{names}: trial {rec.env} {rec.speed:g} m/s #{rec.trial} of {policy!r} was flown with "
                              f"other weights (policy_id {rec.setup.get('policy_id')}), not the checkpoint's; "
                              "nothing published")
    protocol = {"eval_seed": {r.setup.get("sweep_seed") for r in found}, "scene_preset": {r.preset for r in found},
                "physics": {r.extra.get("physics") for r in found}, "backend": {r.extra.get("backend") for r in found}}
    mixed = {k: sorted(map(str, v)) for k, v in protocol.items() if len(v) > 1}
    if mixed:
        what = "; ".join(f"{k} {', '.join(v)}" for k, v in mixed.items())
        raise VitflyError(f"{names}: the trials of {policy!r} mix {what}; publish numbers of one protocol")
    head = {k: next(iter(v)) for k, v in protocol.items()}
    return {"eval_seed": head["eval_seed"], "scene_preset": head["scene_preset"], "success": "no collision",
            "physics": head["physics"], "backend": head["backend"], **closed_loop_cells(summarize(found), policy)}
