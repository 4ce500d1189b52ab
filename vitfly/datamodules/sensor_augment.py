"""Sensor-model domain randomisation: stored exact frames turned into modelled ones (e.g. a D435) on the fly.

A dataset stores the camera's exact render as uint8 u = round(255 x clip(z / depth_max_m, 0, 1)). For a
training item chosen by a seeded coin (probability ``sensor_prob`` per trajectory or window and epoch) every
valid frame goes through:

1. the inverse of the stored normalisation: z = u / 255 x depth_max_m (metres; within half a step,
   depth_max_m / 510 = 2 cm at 10 m). u = 255 stands for everything the clip lost, depth >= depth_max_m or
   nothing hit; it becomes ``inf`` (no surface), which the D435 model reads as "no depth" (beyond its 10 m
   maximum) and deploys as 0.8, the value a valid 10 m reading deploys as too, so nothing the network sees
   is lost. u = 0 (inside an obstacle) stays 0: "no depth" as well;
2. the stereo model of :mod:`vitfly.sensors.stereo` (disparity noise and quantisation, ranges, occlusion
   shadow, propellers), seeded by (split seed, epoch, trajectory) and the frame's tick in its trajectory, so a
   rerun, a resume or another worker count gives the same frames;
3. the deployment normalisation the model ends with (clip(z / 10 m, 0, 1 / 0.8) x 0.8, no depth -> 0.8): the
   frame the network sees in flight with ``vitfly evaluate --sensor d435``;
4. ``delay_ticks`` > 0: frame t shows the modelled frame of tick t - delay (the item's first frame before
   that, as ``FrameDelay`` at the start of a flight).

The batch goes in with depth as stored (uint8) or as float in [0, 1] and comes out float32; items not chosen
keep their exact frames, padding stays 0. Mirroring runs first, so a mirrored flight's occlusion shadow
falls on the side the (unmirrored) camera puts it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from vitfly.datamodules.augment import item_coins
from vitfly.errors import VitflyError
from vitfly.sensors.stereo import ImageGeometry, StereoDepthConfig, StereoDepthSensor, sensor_from_dict

_COIN_SALT, _SEED_SALT = 0x5E11, 0x5EED  # keep these draws apart from the mirror coin's


def check_sensor(values: Mapping[str, Any] | None, prob: float) -> StereoDepthConfig | None:
    """The validated ``data.sensor`` (None when off); one VitflyError line naming the field otherwise."""
    if not 0.0 <= float(prob) <= 1.0:
        raise VitflyError(f"data.sensor_prob: expected a probability in [0, 1], got {prob}")
    try:
        config = sensor_from_dict(values, "data.sensor.")
    except ValueError as err:
        raise VitflyError(str(err)) from None
    if config is None and prob > 0:
        raise VitflyError(f"data.sensor: sensor_prob is {prob} but no sensor model is set; "
                          "expected e.g. {model: d435}")
    return config


def sensor_coins(traj_index: torch.Tensor, start: torch.Tensor, prob: float, seed: int, epoch: int) -> torch.Tensor:
    """(B,) bool: model item b's frames with probability ``prob`` (``item_coins`` with this module's salt)."""
    return item_coins(traj_index, start, prob, seed, epoch, salt=(_COIN_SALT,))


def item_seed(seed: int, epoch: int, traj_index: int) -> int:
    """The sensor seed of one trajectory in one epoch (its speckle pattern; ticks vary the temporal noise)."""
    return int(np.random.SeedSequence([int(seed), int(epoch), int(traj_index), _SEED_SALT]).generate_state(1)[0])


CLIPPED = 254.5 / 255  # normalised values above this were stored as 255: at or beyond the range (float32 safe)


def stored_to_metric(unit: np.ndarray, depth_max_m: float) -> np.ndarray:
    """Metric depth (m, float64) from normalised stored depth in [0, 1]; the clip (255) -> ``inf``."""
    unit = np.asarray(unit, dtype=np.float64)
    return np.where(unit > CLIPPED, np.inf, unit * depth_max_m)


class SensorRandomisation:
    """Applies a sensor model to chosen items of a training batch (see the module docstring).

    ``camera``: the dataset's recorded camera (plain values, None: vitfly's default camera) and
    ``depth_max_m`` its normalisation range."""

    def __init__(self, config: StereoDepthConfig, prob: float, camera: Mapping[str, Any] | None, depth_max_m: float):
        self.config, self.prob, self.depth_max_m = config, float(prob), float(depth_max_m)
        self.sensor = StereoDepthSensor(config, ImageGeometry.from_camera_values(camera, depth_max_m))

    def frames(self, unit: np.ndarray, seed: int, first_tick: int) -> np.ndarray:
        """Modelled frames (T, H, W) float32 of one item's exact normalised frames ``unit`` (T, H, W); frame t is
        tick ``first_tick + t`` of its trajectory."""
        out = np.stack([self.sensor.image(stored_to_metric(frame, self.depth_max_m), seed, first_tick + t)
                        for t, frame in enumerate(unit)])
        delay = int(self.config.delay_ticks)
        if delay:
            out = out[np.maximum(np.arange(len(out)) - delay, 0)]
        return out

    def __call__(self, batch: dict[str, torch.Tensor], seed: int, epoch: int) -> dict[str, torch.Tensor]:
        """The batch with depth as float32 and the chosen items' valid frames modelled; a new dict."""
        if self.prob <= 0.0:
            return batch
        start = batch.get("start", torch.zeros_like(batch["traj_index"]))
        chosen = sensor_coins(batch["traj_index"], start, self.prob, seed, epoch)
        out = dict(batch)
        depth = batch["depth"]
        depth = depth.to(torch.float32) / 255.0 if depth.dtype == torch.uint8 else depth.clone()
        for b in chosen.nonzero().flatten().tolist():
            n = int(batch["mask"][b].sum())  # valid steps come first, padding after
            exact = depth[b, :n, 0].cpu().numpy()
            modelled = self.frames(exact, item_seed(seed, epoch, int(batch["traj_index"][b])), int(start[b]))
            depth[b, :n, 0] = torch.from_numpy(modelled).to(depth.device)
        out["depth"] = depth
        return out
