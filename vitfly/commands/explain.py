"""``vitfly explain``: what the networks look at over one trial (maps, PNG strips, GIFs, numbers); with ``--trials N``
the numbers over N flown trials (scene seeds ``--seed`` .. ``--seed`` + N - 1, the figures of the first) and every
model paired with the first ``--policy`` (``vitfly.eval.explain.study``)."""

from __future__ import annotations

import argparse

from vitfly.sim.scenes import ENVS, PRESETS

SIM_FLAGS = ("env", "preset", "seed", "speed", "pilot", "sensor")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--policy", action="extend", nargs="+", required=True, metavar="SPEC",
                        help="networks to explain, on the same frames: checkpoint paths, or random:NAME "
                        "(architecture NAME with random weights, labelled so)")
    parser.add_argument("--name", action="extend", nargs="+", metavar="LABEL", help="labels, in --policy order")
    parser.add_argument("--out", required=True, help="output directory")
    sim = parser.add_argument_group("fly one trial (default)")
    sim.add_argument("--env", choices=ENVS, help="scene family (default spheres)")
    sim.add_argument("--preset", choices=PRESETS, help="obstacle density (default medium)")
    sim.add_argument("--seed", type=int, help="scene seed (default 0)")
    sim.add_argument("--speed", type=float, help="desired speed, m/s (default 5)")
    sim.add_argument("--pilot", choices=("expert", "straight", "policy"),
                     help="who flies: the expert, straight ahead, or the first --policy (default expert)")
    sim.add_argument("--sensor", nargs="+", metavar="MODEL|FIELD=VALUE",
                     help="stereo sensor model on the rendered depth, e.g. --sensor d435 (vitfly.sim.sensor_models; "
                     "the models see its frames; edges stay exact, from the scene)")
    data = parser.add_argument_group("or replay a recorded trajectory")
    data.add_argument("--data", help="a vitfly HDF5 dataset")
    data.add_argument("--trajectory", type=int, default=0, help="trajectory index in --data")
    study = parser.add_argument_group("several trials, paired (flown trials only)")
    study.add_argument("--trials", type=int, default=1,
                       help="fly N trials (scene seeds --seed .. --seed + N - 1): figures of the first, numbers of all "
                       "in trials.csv, each model minus the first --policy in paired.json / paired.md")
    study.add_argument("--stop-past-obstacles", action="store_true",
                       help="explain each trial only until the drone has passed every obstacle's far face")
    study.add_argument("--compare-map", default="command",
                       help="the map kind the paired comparison uses (the same for both models)")
    parser.add_argument("--frames", type=int, default=8, help="ticks in the PNG strips (evenly spread)")
    parser.add_argument("--ticks", type=int, nargs="+", help="explicit ticks for the PNG strips")
    parser.add_argument("--max-ticks", type=int, help="explain only the first N ticks of the trial")
    parser.add_argument("--no-gif", action="store_true", help="skip the GIFs")
    parser.add_argument("--gif-stride", type=int, default=1, help="use every N-th tick in the GIFs")
    parser.add_argument("--edge-jump", type=float, default=0.5, help="depth jump that makes an obstacle edge, m")
    parser.add_argument("--edge-width", type=int, default=1, help="edge mask dilation, pixels")
    parser.add_argument("--device", default="cpu", help="torch device for the networks")
    parser.add_argument("--init-seed", type=int, default=0, help="seed of the random:NAME weights")


def _recorded_frames(args, edge_config):
    from vitfly.datamodules.schema import open_trajectories
    from vitfly.errors import VitflyError
    from vitfly.eval.explain import frames_from_arrays, scene_from_dataset_config

    with open_trajectories(args.data) as tf:
        if not 0 <= args.trajectory < len(tf):
            raise VitflyError(f"{args.data}: --trajectory {args.trajectory} out of range; it holds {len(tf)} "
                              "trajectories")
        meta = tf.meta(args.trajectory)
        arrays = tf.read(args.trajectory, ("depth", "desired_speed", "quat", "time", "position", "velocity_cmd"))
        scene, camera = scene_from_dataset_config(tf.config, meta["env"], meta["seed"])
        title = (f"{args.data} trajectory {args.trajectory}: {meta['env']} seed {meta['seed']}, "
                 f"{meta['desired_speed']:g} m/s, expert's recorded flight")
        return frames_from_arrays(arrays, tf.depth_max_m, scene, camera, edge_config, title,
                                  {"data": str(args.data), "trajectory": args.trajectory, "pilot": "recorded expert",
                                   **meta})  # fmt: skip


def _flown_frames(args, policies, edge_config, seed=None):
    from vitfly.errors import VitflyError
    from vitfly.eval.explain import fly_trial
    from vitfly.eval.learned_policy import LearnedPolicy
    from vitfly.sim.policies import make_builtin_policy
    from vitfly.sim.rollout import RolloutConfig
    from vitfly.sim.scenes import make_scene

    speed = 5.0 if args.speed is None else args.speed
    if speed <= 0:
        raise VitflyError(f"--speed must be > 0 m/s, got {speed}")
    pilot_name = args.pilot or "expert"
    if pilot_name == "policy":
        pilot, pilot_name = LearnedPolicy(policies[0].net, device=args.device), policies[0].label
    else:
        pilot = make_builtin_policy(pilot_name)
    if seed is None:
        seed = 0 if args.seed is None else args.seed
    scene = make_scene(args.env or "spheres", args.preset or "medium", seed)
    frames = fly_trial(scene, speed, pilot, pilot_name, RolloutConfig(sensor=_sensor(args)), edge_config)
    if args.stop_past_obstacles:
        from vitfly.eval.explain.study import ticks_before_passing

        frames = frames.head(max(ticks_before_passing(frames, scene), 2))
    if args.max_ticks is not None:
        frames = frames.head(args.max_ticks)
    return frames


def _sensor(args):
    """The ``--sensor`` model (None: the ideal camera); a bad field or value is one VitflyError line."""
    from vitfly.errors import VitflyError
    from vitfly.sim.sensor_models import sensor_flag_values, sensor_from_dict

    try:
        return sensor_from_dict(sensor_flag_values(args.sensor))
    except ValueError as err:
        raise VitflyError(f"--sensor: {err}") from None


def _number(v, fmt: str) -> str:
    width = fmt.split(".")[0]
    return format(v, fmt) if isinstance(v, float) and v == v else format("-", f">{width}")


def run(args: argparse.Namespace) -> int:
    from vitfly.errors import VitflyError
    from vitfly.eval.explain import EdgeConfig, explain_trial, load_policies

    if args.data is not None:
        given = [f"--{f}" for f in SIM_FLAGS if getattr(args, f) is not None]
        if given:
            raise VitflyError(f"--data replays a recorded trajectory; {', '.join(given)} only apply to a flown trial")
    if args.edge_jump <= 0 or args.edge_width < 0:
        raise VitflyError("--edge-jump must be > 0 m and --edge-width >= 0 pixels")
    if args.max_ticks is not None and args.max_ticks < 2:
        raise VitflyError(f"--max-ticks must be >= 2, got {args.max_ticks}")
    if args.trials < 1:
        raise VitflyError(f"--trials must be >= 1, got {args.trials}")
    if args.data is not None and (args.trials > 1 or args.stop_past_obstacles):
        raise VitflyError("--data replays one recorded trajectory; --trials and --stop-past-obstacles apply to flown "
                          "trials")
    if args.data is None:
        _sensor(args)  # a bad --sensor is one line before anything loads or flies
    policies = load_policies(args.policy, args.name, args.init_seed)
    if args.trials > 1:
        _check_compare_map(args.compare_map, policies)
    edge_config = EdgeConfig(jump_m=args.edge_jump, width_px=args.edge_width)
    if args.data is not None:
        frames = _recorded_frames(args, edge_config)
        if args.max_ticks is not None:
            frames = frames.head(args.max_ticks)
    else:
        frames = _flown_frames(args, policies, edge_config)
    print(frames.title)
    if frames.info.get("edge_note"):
        print(f"note: {frames.info['edge_note']}")
    result = explain_trial(policies, frames, args.out, ticks=args.ticks, n_frames=args.frames, gif=not args.no_gif,
                           gif_stride=args.gif_stride, device=args.device, progress=lambda s: print(s, flush=True))
    print(f"{'model':<28} {'map':<18} {'consistency':>11} {'edge mass':>9} {'edge area':>9} {'lift':>5}")
    for r in result.rows():
        cells = [_number(r.get(k), f) for k, f in (("consistency", "11.3f"), ("edge_mass_share", "9.3f"),
                                                   ("edge_area_share", "9.3f"), ("edge_lift", "5.2f"))]
        print(f"{r['model']:<28} {r['map']:<18} " + " ".join(cells))
    print("wrote " + ", ".join(str(p) for p in result.files.values()))
    if args.trials > 1:
        _study(args, policies, edge_config, result)
    return 0


def _check_compare_map(kind: str, policies) -> None:
    """One line, before anything is flown, when a policy cannot make the map kind the comparison uses."""
    from vitfly.errors import VitflyError
    from vitfly.eval.explain.maps import GRADCAM_MAPS, attention_layers, spatial_layers

    for p in policies:
        stages = len(attention_layers(p.net))
        kinds = (list(GRADCAM_MAPS) if spatial_layers(p.net) else []) + (
            ["attention", *(f"attention_stage{i}" for i in range(stages))] if stages else [])
        if kind not in kinds:
            raise VitflyError(f"--compare-map {kind}: {p.label} has no such map (it has {', '.join(kinds)}); "
                              "compare a map kind every --policy has")


def _study(args, policies, edge_config, first) -> None:
    """Trials 2..N, the per-trial numbers (trials.csv) and each model minus the first (paired.json, paired.md)."""
    import csv
    import io
    import json
    from pathlib import Path

    from vitfly.atomic import write_text
    from vitfly.eval.explain.study import TRIAL_COLUMNS, map_finding, run_study

    seed0 = 0 if args.seed is None else args.seed
    rows = [{"seed": seed0, **{k: v for k, v in r.items() if k in TRIAL_COLUMNS}} for r in first.rows()]
    trials = [(s, lambda s=s: _flown_frames(args, policies, edge_config, seed=s))
              for s in range(seed0 + 1, seed0 + args.trials)]
    rows += run_study(policies, trials, args.device, progress=lambda s: print(s, flush=True))
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=TRIAL_COLUMNS, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    out = Path(args.out)
    write_text(out / "trials.csv", buf.getvalue())
    base = policies[0].label
    findings = [map_finding(rows, p.label, base, args.compare_map) for p in policies[1:]]
    lines = [f"| model minus {base} | map | metric | mean model | mean {base} | difference [95 %], trials | decided |",
             "|---|---|---|---:|---:|---|---|"]
    for f in findings:
        for c in f["comparisons"]:
            lines.append(f"| {c['a']} | {c['map_kind']} | {c['metric']} | {c['mean_a']:.3f} | {c['mean_b']:.3f} | "
                         f"{c['diff']:+.3f} [{c['low']:+.3f}, {c['high']:+.3f}], {c['trials']} | {c['side']} |")
    lines += [f"\n{f['a']} vs {base}: **{f['verdict']}** ({f['why']})" for f in findings]
    text = "\n".join(lines) + "\n"
    write_text(out / "paired.md", text)
    write_text(out / "paired.json", json.dumps({"trials": args.trials, "first_seed": seed0, "findings": findings},
                                               indent=1) + "\n")
    print(text)
    print(f"wrote {out / 'trials.csv'}, {out / 'paired.md'}, {out / 'paired.json'}")
