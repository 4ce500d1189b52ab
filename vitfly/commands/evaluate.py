"""``vitfly evaluate``: fly a policy closed-loop over envs x speeds x trials and score it (resumable).

Trials are keyed by what was flown (the policy's content, --seed, --preset, the rollout settings):
an identical rerun resumes; a rerun into the same --out under the same label with anything of
that changed is refused with one line, or replaces the stale trials with --overwrite.
"""

from __future__ import annotations

import argparse

from vitfly.commands.engine_flags import add_engine_arguments
from vitfly.eval.config import BACKENDS, load_sweep_config
from vitfly.sim.scenes import ENVS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="evaluation YAML: a path, or a shipped config's name (e.g. eval/spheres); "
                        "flags override it")
    parser.add_argument("--policy", help="a checkpoint path, 'pretrained:NAME' (shipped weights, e.g. "
                        "pretrained:vit_lstm), 'modular:NAME' (a modular baseline: fastplanner, fastplanner_scaled, "
                        "convex, convex_scaled), 'expert' or 'straight' (config default: expert)")
    parser.add_argument("--planner-config", help="modular:NAME: planners YAML, a path or a shipped config's name "
                        "(default: planners, i.e. configs/planners.yaml)")
    parser.add_argument("--arch", help="architecture of an original-project checkpoint (e.g. vit_lstm)")
    parser.add_argument("--name", help="policy label in the reports (default: expert/straight/checkpoint stem)")
    parser.add_argument("--env", nargs="+", choices=ENVS, help="environment(s) (config default: spheres)")
    parser.add_argument("--preset", help="scene density preset: easy, medium, hard")
    parser.add_argument("--speeds", type=float, nargs="+", help="desired speeds, m/s (config default: 3 4 5 6 7)")
    parser.add_argument("--trials", type=int, help="trials per (env, speed) (config default: 10)")
    parser.add_argument("--seed", type=int, help="sweep seed: scene seeds derive from (seed, env, trial)")
    parser.add_argument("--out", help="output directory: trials.jsonl, summary.csv/.md, plots (default runs/eval)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace this label's trials in --out that were flown with another checkpoint, seed, "
                             "preset or rollout settings (default: refuse)")
    parser.add_argument("--num-envs", type=int, help="scenes stepped in lockstep per batched policy call")
    parser.add_argument("--workers", type=int, help="worker processes")
    parser.add_argument("--shard", help="i/n: fly only shard i (0-based) of n; shards' outputs merge")
    parser.add_argument("--device", help="device of learned policies' batched network: cpu or cuda[:N] "
                                         "(with --sim batched --sim-device on the same card, observations stay on it)")
    parser.add_argument("--threads", type=int, help="torch threads per worker")
    parser.add_argument("--backend", choices=BACKENDS,
                        help="inference back end of learned policies (compiled: eager with the image encoder "
                             "through torch.compile, compiled on the first call; onnxruntime-int8: int8 products)")
    parser.add_argument("--physics", choices=("auto", "pybullet", "native"),
                        help="rigid-body physics back end, stated in every trial record (config default: auto, "
                             "pybullet where installed, else native)")
    add_engine_arguments(parser, "the trials")
    parser.add_argument("--timeout", type=float, dest="timeout_s", help="trial timeout, s (default: scales w/ speed)")
    parser.add_argument("--camera", nargs="+", metavar="FIELD=VALUE", type=_camera_setting,
                        help="camera settings (e.g. vertical_fov_deg=70, or preset=camera_config_yaml); "
                             "default: the checkpoint's training camera")
    parser.add_argument("--control-hz", type=float, help="policy and camera rate, Hz (default: the checkpoint's)")
    parser.add_argument("--depth-max-m", type=float, help="depth range, m (default: the checkpoint's)")
    parser.add_argument("--override-sensor", action="store_true", default=None,
                        help="fly with --camera/--control-hz/--depth-max-m even where they contradict the checkpoint")
    parser.add_argument("--sensor", nargs="+", metavar="MODEL|FIELD=VALUE",
                        help="stereo sensor model on the rendered depth, e.g. --sensor d435 delay_ticks=1 "
                             "(vitfly.sim.sensor_models; none: the ideal camera, the default)")
    parser.add_argument("--no-gif", action="store_true", help="skip the depth GIF with the command arrow")
    parser.add_argument("--no-plots", action="store_true", help="skip the plots")
    parser.add_argument("--wandb-project", help="also log the summary and plots to this wandb project")
    parser.add_argument("--merge", nargs="+", metavar="DIR",
                        help="only merge the trials of these directories into --out and write its reports (into a "
                             "published folder, its outcomes.jsonl.gz alone, without their paths)")
    parser.add_argument("--report-only", action="store_true",
                        help="only (re)write the reports of --out (from its trials*.jsonl, else its outcomes.jsonl.gz)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _camera_setting(text: str) -> tuple[str, object]:
    """FIELD=VALUE, the value read as YAML (numbers, true/false, [0, 0, 0.3])."""
    import yaml

    field, sep, value = text.partition("=")
    if not sep or not field:
        raise argparse.ArgumentTypeError(f"expected FIELD=VALUE, got {text!r}")
    try:
        return field.strip(), yaml.safe_load(value)
    except yaml.YAMLError:
        raise argparse.ArgumentTypeError(f"{field}: cannot read value {value!r}") from None


def run(args: argparse.Namespace) -> int:
    from vitfly.errors import VitflyError
    from vitfly.eval.evaluation import merge_into, run_evaluation, write_outputs
    from vitfly.eval.policy_source import PolicySource
    from vitfly.eval.report import print_table, summary_title
    from vitfly.eval.sensor import resolve_sensor
    from vitfly.sim.sensor_models import sensor_flag_values

    overrides = {k: getattr(args, k) for k in ("policy", "arch", "name", "env", "preset", "speeds", "trials", "seed",
                                              "out", "num_envs", "workers", "shard", "device", "threads",
                                              "backend", "physics", "sim", "sim_device", "sim_dtype", "sim_compile",
                                              "timeout_s",
                                              "wandb_project", "control_hz", "depth_max_m", "override_sensor")}
    overrides["planner_config"] = args.planner_config
    overrides["camera"] = dict(args.camera) if args.camera else None
    try:
        overrides["sensor"] = sensor_flag_values(args.sensor)
    except ValueError as err:
        raise VitflyError(str(err)) from None
    overrides["gif"] = False if args.no_gif else None
    overrides["plots"] = False if args.no_plots else None
    overrides["overwrite"] = True if args.overwrite else None
    cfg = load_sweep_config(args.config, overrides)
    if not (args.merge or args.report_only):
        source = PolicySource(cfg.policy, cfg.arch, planner_config=cfg.planner_config)
        source.check()
        cfg, note = resolve_sensor(cfg, source.trained_sensor(), cfg.policy)
        # the built-in policies and the planners fly the defaults or the options, nothing to report
        if not (source.is_builtin or source.is_modular):
            print(note)
    if args.merge or args.report_only:
        if args.merge:
            print(f"{cfg.out}: merged {merge_into(cfg.out, args.merge)} new trials")
        rows, files = write_outputs(cfg.out, cfg.plots, title=summary_title(cfg.out))
    else:
        result = run_evaluation(cfg, progress=not args.no_progress)
        rows, files = result.rows, result.files
        o = result.outcome
        replaced = f", {o.replaced} of another setup replaced" if o.replaced else ""
        print(f"{cfg.label}: {o.flown} trials flown, {o.skipped} already done{replaced}, {o.wall_s:.1f} s")
    print_table(rows, title=f"closed-loop evaluation ({cfg.out})")
    print("wrote " + ", ".join(str(p) for p in files.values()))
    return 0
