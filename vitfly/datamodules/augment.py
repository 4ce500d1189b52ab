"""Label-preserving augmentation: the world mirrored left-right (y -> -y).

Mirroring the world in the x-z plane (M = diag(1, -1, 1)) maps a scene, the drone and its flight to
another valid flight, and each piece of a training step changes as follows:

- depth image: a point's body-frame coordinates b = R^T (p - c) become M b, so the image is flipped
  left-right (the camera's pixel columns are symmetric about its optical axis);
- velocity command (world frame, the label): y -> -y;
- attitude, body-to-world quaternion (w, x, y, z): the rotation R becomes M R M, a rotation by the same
  angle about the axis -M n, i.e. (w, x, y, z) -> (w, -x, y, -z);
- desired speed: unchanged.

``mirror_items`` applies this to chosen items of a batch (whole trajectories or windows at once, so a
recurrent network sees one consistent mirrored flight); ``random_mirror`` chooses the items with a coin
per (seed, epoch, trajectory, window start), so the choice does not depend on batch order, DataLoader
workers or a resume.
"""

from __future__ import annotations

import numpy as np
import torch

from vitfly.errors import VitflyError

QUAT_MIRROR_SIGN = (1.0, -1.0, 1.0, -1.0)  # (w, x, y, z) -> (w, -x, y, -z)
VELOCITY_MIRROR_SIGN = (1.0, -1.0, 1.0)  # world (x, y, z) -> (x, -y, z)


def check_mirror_prob(prob: float, source: str = "mirror_prob") -> float:
    if not 0.0 <= float(prob) <= 1.0:
        raise VitflyError(f"{source}: expected a probability in [0, 1], got {prob}")
    return float(prob)


def mirror_items(batch: dict[str, torch.Tensor], flip: torch.Tensor) -> dict[str, torch.Tensor]:
    """The batch with items ``flip`` (B,) bool mirrored left-right; a new dict, the input is not changed.

    ``depth`` (B, T, 1, H, W) any dtype; ``quat`` (B, T, 4) (w, x, y, z); ``velocity_cmd`` (B, T, 3)
    world frame. Padding stays zero; other keys pass through.
    """
    out = dict(batch)
    if not bool(flip.any()):
        return out
    idx = flip.nonzero().flatten().to(batch["depth"].device, non_blocking=True)
    depth = batch["depth"].clone()
    depth[idx] = depth[idx].flip(-1)
    out["depth"] = depth
    for key, sign in (("quat", QUAT_MIRROR_SIGN), ("velocity_cmd", VELOCITY_MIRROR_SIGN)):
        values = batch[key].clone()
        values[idx] = values[idx] * values.new_tensor(sign)
        out[key] = values
    return out


def item_coins(traj_index: torch.Tensor, start: torch.Tensor, prob: float, seed: int, epoch: int,
               salt: tuple[int, ...] = ()) -> torch.Tensor:
    """(B,) bool: True for item b with probability ``prob``, a fixed draw per (seed, epoch, trajectory, start,
    *salt), so reruns, resumes and worker counts agree; a different ``salt`` keeps another augmentation's draws
    apart. An item without a trajectory (index < 0) is never chosen."""
    draws = [np.random.default_rng([int(seed), int(epoch), int(m), int(s), *salt]).random() if m >= 0 else 1.0
             for m, s in zip(traj_index.tolist(), start.tolist(), strict=True)]
    return torch.tensor(draws) < prob


def mirror_coins(traj_index: torch.Tensor, start: torch.Tensor, prob: float, seed: int, epoch: int) -> torch.Tensor:
    """(B,) bool: mirror item b with probability ``prob`` (``item_coins`` without a salt)."""
    return item_coins(traj_index, start, prob, seed, epoch)


def random_mirror(batch: dict[str, torch.Tensor], prob: float, seed: int, epoch: int,
                  coins: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Mirror each item of the batch with probability ``prob`` (see ``mirror_coins``). ``coins``: the batch's
    ``mirror_coins`` drawn already (on the host, before the batch went to a device, so that drawing them here
    does not wait for the device to hand its ``traj_index`` back)."""
    if prob <= 0.0:
        return batch
    if coins is None:
        coins = batch_coins(batch, prob, seed, epoch)
    return mirror_items(batch, coins)


def batch_coins(batch: dict[str, torch.Tensor], prob: float, seed: int, epoch: int) -> torch.Tensor:
    """``mirror_coins`` of a batch's items (its ``traj_index`` and window ``start``; 0 without one)."""
    start = batch.get("start", torch.zeros_like(batch["traj_index"]))
    return mirror_coins(batch["traj_index"], start, prob, seed, epoch)
