"""Clean vs d435-modelled depth frames of the same poses (docs/sensor_d435.png).

    .venv/bin/python benchmarks/sensor_figure.py --out docs/sensor_d435.png

Rows: a course scene (gap layout) and a spheres scene; columns: the camera's exact render (what the
networks are trained on), the d435 model with the original's deployment values (invalid -> 0.8,
depth x 0.8), and the same with propeller blades in the top corners reading near. Black-to-white = near-to-far
(normalised depth 0..1).
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from vitfly.sim.camera import CameraConfig, DepthCamera  # noqa: E402
from vitfly.sim.scenes import make_scene  # noqa: E402
from vitfly.sim.sensor_models import StereoDepthConfig, StereoDepthSensor  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default="docs/sensor_d435.png")
    args = parser.parse_args()
    cam_cfg = CameraConfig()
    camera = DepthCamera(cam_cfg)
    poses = [(make_scene("course", "gap", 2), (3.0, 0.0, 3.5)), (make_scene("spheres", "medium", 3), (9.0, 0.0, 3.5))]
    sensors = [("d435 (default)", StereoDepthSensor(StereoDepthConfig(), cam_cfg)),
               ("d435, propellers: top, reads near",
                StereoDepthSensor(StereoDepthConfig(propellers="top", propeller_reads="near"), cam_cfg))]
    fig, axes = plt.subplots(len(poses), 1 + len(sensors), figsize=(11, 4.6))
    for row, (scene, position) in enumerate(poses):
        metric = camera.metric_depth(scene, position, np.eye(3))
        clean = np.minimum(metric / cam_cfg.max_range_m, 1.0)
        frames = [("exact render", clean)] + [(name, s.image(metric, scene.seed, 0)) for name, s in sensors]
        for col, (name, frame) in enumerate(frames):
            ax = axes[row, col]
            ax.imshow(frame, cmap="gray", vmin=0.0, vmax=1.0, interpolation="nearest")
            ax.set_title(f"{scene.env}/{scene.preset}: {name}", fontsize=8)
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
