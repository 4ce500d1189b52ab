"""How early a policy starts to avoid: the paper's real-flight claim "ViT+LSTM avoids earlier than ConvNet".

On a single-obstacle course scene (``course`` preset ``easy`` = ``single``: one cylinder or box standing on the
start line) a policy flies straight at first; the **avoidance onset** is the first control tick at which its
lateral (world y) velocity command departs from straight flight, and the **onset distance** the drone's distance
to the obstacle's surface at that tick. A larger onset distance is an earlier avoidance.

- **Threshold**: |v_y command| > ``threshold_fraction`` x desired speed, 0.1 by default (a heading 5.7 degrees
  off the line; 0.3 m/s at 3 m/s, 0.7 m/s at 7 m/s). The deployment normalises every command to the desired
  speed, so a fraction of the speed is the same turn at every speed. In empty space the shipped networks'
  lateral commands stay below 0.02 x speed with exact depth (99th percentile; ``straight_floor`` measures it past
  the obstacle), so 0.1 is five times that floor and well below a real avoidance (0.3-0.6 x speed). With the
  D435 model ConvNet's floor rises to about 0.1 (docs/results.md): check the floor before trusting an onset.
- **Distance**: Euclidean, from the drone's centre to the nearest point of the obstacle's solid (cylinder: radial
  and vertical excess; box: per-axis excess), 0 inside. The columns are 8 m tall and the drone flies at about
  3.5 m, so this is the horizontal distance to the surface.
- **Window**: only ticks before the drone comes abeam of the obstacle (its x below the obstacle's near face) and
  with the obstacle within the camera's range (``range_m``, 10 m: farther, the camera cannot see it, so a
  departure there is no reaction to it). A policy that never departs in the window gets onset distance 0 (it
  did not turn before reaching the obstacle) and ``departed`` False.

``onset_table`` reads evaluation records (``vitfly evaluate --env course --preset easy``; the per-tick ``path``
holds position and command) and ``paired_onset`` gives policy A minus policy B over the same scenes with the
scene bootstrap of ``vitfly.eval.paired`` (95 %, BCa).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from vitfly.errors import VitflyError
from vitfly.eval.paired import claim_side, scene_bootstrap_interval
from vitfly.eval.records import TrialRecord
from vitfly.sim.collision import signed_distances
from vitfly.sim.scenes import Scene, make_scene

THRESHOLD_FRACTION = 0.1  # of the desired speed
RANGE_M = 10.0  # the camera's range (CameraConfig.max_range_m)
FLOOR_CLEARANCE_M = 5.0  # straight_floor: ticks this far past the obstacle's far face (nothing left to avoid)


def single_obstacle(scene: Scene, where: str = "scene") -> tuple[str, np.ndarray]:
    """("cylinder", [x, y, z_bottom, z_top, r]) or ("box", [x_min, y_min, z_min, x_max, y_max, z_max]) of a scene
    with exactly one obstacle; VitflyError otherwise (the onset needs the course's single layout)."""
    if scene.num_obstacles != 1 or len(scene.spheres):
        raise VitflyError(f"{where}: {scene.env}/{scene.preset} seed {scene.seed} has {scene.num_obstacles} "
                          "obstacles; the avoidance onset needs one cylinder or box (--env course --preset easy)")
    if len(scene.cylinders):
        return "cylinder", scene.cylinders[0]
    return "box", scene.boxes[0]


def obstacle_x_extent(kind: str, shape: np.ndarray) -> tuple[float, float]:
    """(near face x, far face x) of the obstacle, m."""
    if kind == "cylinder":
        return float(shape[0] - shape[4]), float(shape[0] + shape[4])
    return float(shape[0]), float(shape[3])


def distance_to_surface_m(position_m: np.ndarray, kind: str, shape: np.ndarray) -> np.ndarray:
    """(T,) Euclidean distance (m) from each world-frame position (T, 3) to the obstacle's solid, 0 inside (the
    simulator's own geometry, ``vitfly.sim.collision.signed_distances``)."""
    if kind not in ("cylinder", "box"):
        raise VitflyError(f"obstacle kind {kind!r}: expected cylinder or box")
    empty = np.zeros((0, 4))
    scene = Scene(env="course", preset="easy", seed=0, spheres=empty,
                  cylinders=shape if kind == "cylinder" else np.zeros((0, 5)),
                  boxes=shape if kind == "box" else np.zeros((0, 6)))
    p = np.asarray(position_m, dtype=np.float64).reshape(-1, 3)
    return np.maximum(np.array([signed_distances(q, scene)[0] for q in p]), 0.0)


@dataclass(frozen=True)
class Onset:
    """One trial's avoidance onset: ``distance_m`` (0 when it never departed in the window), the tick and time
    (s) of the onset (None / nan when it never departed), the lateral command there (m/s, world y), and how many
    ticks the window held."""

    distance_m: float
    departed: bool
    tick: int | None
    time_s: float
    command_y_mps: float
    window_ticks: int


def avoidance_onset(
    time_s: np.ndarray,
    position_m: np.ndarray,
    command_mps: np.ndarray,
    desired_speed_mps: float,
    kind: str,
    shape: np.ndarray,
    threshold_fraction: float = THRESHOLD_FRACTION,
    range_m: float = RANGE_M,
) -> Onset:
    """The onset of one flown path (time (T,) s, position (T, 3) m, command (T, 3) m/s, world frame)."""
    if not threshold_fraction > 0 or not range_m > 0 or not desired_speed_mps > 0:
        raise VitflyError("avoidance onset: threshold_fraction, range_m and the desired speed must be > 0")
    position = np.asarray(position_m, dtype=np.float64).reshape(-1, 3)
    command = np.asarray(command_mps, dtype=np.float64).reshape(-1, 3)
    if len(position) != len(command) or len(position) != len(time_s):
        raise VitflyError(f"avoidance onset: path fields differ in length (time {len(time_s)}, position "
                          f"{len(position)}, command {len(command)})")
    distance = distance_to_surface_m(position, kind, shape)
    near_x, _ = obstacle_x_extent(kind, shape)
    window = (position[:, 0] < near_x) & (distance <= range_m)
    departs = window & (np.abs(command[:, 1]) > threshold_fraction * desired_speed_mps)
    if not departs.any():
        return Onset(0.0, False, None, math.nan, math.nan, int(window.sum()))
    k = int(np.argmax(departs))
    return Onset(float(distance[k]), True, k, float(time_s[k]), float(command[k, 1]), int(window.sum()))


def straight_floor(position_m: np.ndarray, command_mps: np.ndarray, desired_speed_mps: float, kind: str,
                   shape: np.ndarray, clearance_m: float = FLOOR_CLEARANCE_M) -> np.ndarray:
    """|v_y command| / desired speed at the ticks ``clearance_m`` past the obstacle's far face (empty space)."""
    _, far_x = obstacle_x_extent(kind, shape)
    position = np.asarray(position_m, dtype=np.float64).reshape(-1, 3)
    past = position[:, 0] > far_x + clearance_m
    return np.abs(np.asarray(command_mps, dtype=np.float64).reshape(-1, 3)[past, 1]) / desired_speed_mps


def record_onset(rec: TrialRecord, threshold_fraction: float = THRESHOLD_FRACTION, range_m: float = RANGE_M,
                 scene: Scene | None = None) -> Onset:
    """The onset of one trial record (its scene regenerated from env, preset and scene seed)."""
    where = f"trial record {rec.policy} {rec.env} {rec.speed:g} m/s trial {rec.trial}"
    scene = scene or make_scene(rec.env, rec.preset, rec.scene_seed)
    kind, shape = single_obstacle(scene, where)
    p = rec.path_arrays()
    return avoidance_onset(p["time"], p["position"], p["command"], rec.speed, kind, shape, threshold_fraction,
                           range_m)


def onset_table(records: Iterable[TrialRecord], threshold_fraction: float = THRESHOLD_FRACTION,
                range_m: float = RANGE_M) -> dict[tuple[str, float, int], Onset]:
    """{(policy, speed, scene seed): Onset} for every record (scenes generated once each)."""
    scenes: dict[tuple[str, str, int], Scene] = {}
    out = {}
    for rec in records:
        key = (rec.env, rec.preset, rec.scene_seed)
        if key not in scenes:
            scenes[key] = make_scene(*key)
        out[(rec.policy, float(rec.speed), rec.scene_seed)] = record_onset(rec, threshold_fraction, range_m,
                                                                           scenes[key])
    return out


@dataclass(frozen=True)
class OnsetDifference:
    """Policy ``a`` minus policy ``b`` in onset distance (m) over the scenes both flew at ``speeds``: means, the
    mean paired difference with its 95 % scene-bootstrap interval, and the share of trials that departed."""

    a: str
    b: str
    speeds: tuple[float, ...]
    pairs: int
    scenes: int
    mean_a_m: float
    mean_b_m: float
    diff_m: float
    low_m: float
    high_m: float
    departed_a: float
    departed_b: float

    @property
    def side(self) -> str:
        """The claim "a avoids earlier than b": "for", "against" or "undecided" (``vitfly.eval.paired.claim_side``)."""
        return claim_side(self.low_m, self.high_m)

    def text(self) -> str:
        return f"{self.diff_m:+.2f} m [{self.low_m:+.2f}, {self.high_m:+.2f}], {self.pairs} pairs"

    def to_dict(self) -> dict:
        return {**asdict(self), "side": self.side}


def paired_onset(onsets: dict[tuple[str, float, int], Onset], a: str, b: str,
                 speeds: Sequence[float] | None = None, seed: int = 0) -> OnsetDifference | None:
    """``a`` minus ``b`` over the (speed, scene) pairs both flew (``speeds`` default: all); None without pairs.
    Pairs of the same scene at several speeds stay together in the bootstrap (one scene, one draw)."""
    if a == b:
        raise VitflyError(f"paired onset: compare two different policies, got {a!r} twice")
    wanted = None if speeds is None else {float(s) for s in speeds}
    keys = sorted((sp, sc) for (pol, sp, sc) in onsets
                  if pol == a and (b, sp, sc) in onsets and (wanted is None or sp in wanted))
    if not keys:
        return None
    da = np.array([onsets[(a, sp, sc)].distance_m for sp, sc in keys])
    db = np.array([onsets[(b, sp, sc)].distance_m for sp, sc in keys])
    scene = np.array([sc for _, sc in keys], dtype=np.int64)
    low, high = scene_bootstrap_interval(scene, da - db, seed=seed)
    return OnsetDifference(
        a, b, tuple(sorted({sp for sp, _ in keys})), len(keys), len(set(scene.tolist())), float(da.mean()),
        float(db.mean()), float((da - db).mean()), low, high,
        float(np.mean([onsets[(a, *k)].departed for k in keys])),
        float(np.mean([onsets[(b, *k)].departed for k in keys])),
    )


FINDING = "ViT+LSTM avoids earlier than ConvNet (single obstacle)"
RULE = ("onset distance (m) on single-obstacle course scenes, ViT+LSTM minus ConvNet paired over scenes, one claim "
        "per sensor pooled over speeds, decided when its 95 % scene-bootstrap interval excludes 0; all for "
        "reproduced, any against not, some for partly, none decided cannot tell")


def onset_finding(sweeps: dict[str, Sequence[TrialRecord]], a: str = "vit_lstm", b: str = "convnet",
                  threshold_fraction: float = THRESHOLD_FRACTION, range_m: float = RANGE_M) -> dict:
    """The finding over several sensors' sweeps (``{"exact": records, "d435": records}``): per sensor the paired
    difference per speed and pooled, each policy's mean onset per speed, the empty-space floor of |v_y| / speed,
    and the verdict by ``RULE`` (``vitfly.eval.paired.claims_verdict``)."""
    from vitfly.eval.paired import claims_verdict

    out: dict = {"finding": FINDING, "rule": RULE, "a": a, "b": b, "threshold_fraction": threshold_fraction,
                 "range_m": range_m, "sensors": {}}
    sides = []
    for sensor, records in sweeps.items():
        records = list(records)
        onsets = onset_table(records, threshold_fraction, range_m)
        speeds = sorted({sp for _, sp, _ in onsets})
        policies = sorted({pol for pol, _, _ in onsets})
        per_speed = [d.to_dict() for sp in speeds if (d := paired_onset(onsets, a, b, [sp])) is not None]
        pooled = paired_onset(onsets, a, b)
        means = {pol: {f"{sp:g}": float(np.mean([o.distance_m for (p, s, _), o in onsets.items() if p == pol
                                                  and s == sp])) for sp in speeds} for pol in policies}
        for pol in policies:
            means[pol]["all"] = float(np.mean([o.distance_m for (p, _, _), o in onsets.items() if p == pol]))
        floors = {}
        for pol in policies:
            values = []
            for rec in records:
                if rec.policy == pol:
                    kind, shape = single_obstacle(make_scene(rec.env, rec.preset, rec.scene_seed))
                    p = rec.path_arrays()
                    values.append(straight_floor(p["position"], p["command"], rec.speed, kind, shape))
            v = np.concatenate(values) if values else np.zeros(0)
            floors[pol] = {"p99": float(np.percentile(v, 99)) if len(v) else math.nan, "ticks": int(len(v))}
        out["sensors"][sensor] = {"per_speed": per_speed, "pooled": None if pooled is None else pooled.to_dict(),
                                  "mean_onset_m": means, "straight_floor": floors}
        if pooled is not None:
            sides.append(pooled.side)
    out["verdict"], out["why"] = claims_verdict(sides)
    return out


def onset_markdown(finding: dict) -> str:
    """The finding as Markdown: one row per (sensor, speed) and pooled, then the verdict."""
    a, b = finding["a"], finding["b"]
    others = sorted({p for s in finding["sensors"].values() for p in s["mean_onset_m"]} - {a, b})
    lines = [f"| depth | speed | {a} onset (m) | {b} onset (m) | {a} - {b} [95 %], pairs | departed {a} / {b} |"
             + "".join(f" {p} onset (m) |" for p in others),
             "|---|---|---:|---:|---|---:|" + "---:|" * len(others)]
    for sensor, s in finding["sensors"].items():
        rows = [*s["per_speed"], *([s["pooled"]] if s["pooled"] and len(s["per_speed"]) > 1 else [])]
        for d in rows:
            key = "all" if len(d["speeds"]) > 1 else f"{d['speeds'][0]:g}"
            speed = key if key == "all" else f"{key} m/s"
            extra = "".join(f" {s['mean_onset_m'].get(p, {}).get(key, math.nan):.2f} |" for p in others)
            lines.append(f"| {sensor} | {speed} | {d['mean_a_m']:.2f} | {d['mean_b_m']:.2f} | {d['diff_m']:+.2f} "
                         f"[{d['low_m']:+.2f}, {d['high_m']:+.2f}], {d['pairs']} | "
                         f"{100 * d['departed_a']:.0f} % / {100 * d['departed_b']:.0f} % |{extra}")
    lines.append(f"\nVerdict: **{finding['verdict']}** ({finding['why']}). Rule: {finding['rule']}.")
    return "\n".join(lines) + "\n"
