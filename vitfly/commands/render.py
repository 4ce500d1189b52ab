"""``vitfly render``: fly one trial and draw it (top and side views, depth strip; PNG and GIF)."""

from __future__ import annotations

import argparse
from pathlib import Path

from vitfly.sim.camera import CameraConfig
from vitfly.sim.policies import BUILTIN_POLICIES, make_builtin_policy
from vitfly.sim.rollout import RolloutConfig, run_episodes
from vitfly.sim.scenes import ENVS, PRESETS, load_scene, make_scene, save_scene
from vitfly.sim.visualize import episode_figure, save_figure, write_gif


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--env", choices=ENVS, default="spheres", help="scene family")
    parser.add_argument("--preset", choices=PRESETS, default="medium", help="obstacle density")
    parser.add_argument("--seed", type=int, default=0, help="scene seed")
    parser.add_argument(
        "--scene", help="replay a scene JSON (written by --save-scene) instead of --env/--preset/--seed"
    )
    parser.add_argument("--speed", type=float, default=5.0, help="desired speed, m/s")
    parser.add_argument("--policy", choices=sorted(BUILTIN_POLICIES), default="expert", help="who flies")
    parser.add_argument("--out", required=True, help="PNG: top view, side view and a strip of depth frames")
    parser.add_argument("--gif", help="also write a GIF of the whole trial (depth + command arrow)")
    parser.add_argument("--gif-stride", type=int, default=1, help="use every N-th frame in the GIF")
    parser.add_argument("--frames", type=int, default=8, help="depth frames in the PNG strip")
    parser.add_argument("--save-scene", help="write the scene as JSON (to replay the same trial)")
    parser.add_argument("--body-radius", type=float, default=0.0, help="drone radius for contact, m (0: point)")


def run(args: argparse.Namespace) -> int:
    from vitfly.errors import VitflyError
    from vitfly.sim.rollout import TaskConfig

    if args.speed <= 0:
        raise VitflyError(f"--speed must be > 0 m/s, got {args.speed}")
    if args.frames < 1:
        raise VitflyError(f"--frames must be >= 1, got {args.frames}")
    scene = load_scene(args.scene) if args.scene else make_scene(args.env, args.preset, args.seed)
    config = RolloutConfig(camera=CameraConfig(), task=TaskConfig(body_radius_m=args.body_radius), record_depth=True)
    result = run_episodes([scene], [args.speed], make_builtin_policy(args.policy), config)[0]
    s = result.summary
    written = [save_figure(episode_figure(result, n_frames=args.frames), args.out)]
    if args.gif:
        written.append(write_gif(result, args.gif, stride=args.gif_stride))
    if args.save_scene:
        save_scene(scene, args.save_scene)
        written.append(Path(args.save_scene))
    print(
        f"{s.env}/{s.preset} seed {s.seed} at {s.desired_speed:g} m/s ({args.policy}): {s.end_reason} after "
        f"{s.duration_s:.1f} s, {s.n_collisions} collision(s), {s.time_in_contact_s:.2f} s in contact"
    )
    for p in written:
        print(f"wrote {p}")
    return 0
