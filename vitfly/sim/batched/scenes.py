"""Scenes as padded tensors: E scenes of :mod:`vitfly.sim.scenes` in one batch (world frame, m).

The batch is built FROM the scene objects the generators made (``make_scene``, ``load_scene``): nothing
is generated here. Each primitive kind is padded to the largest count in the batch, with a mask saying
which rows are real; padded rows are zeros and every consumer ignores them through the mask.

Example::

    batch = scene_batch([make_scene("trees", "medium", s) for s in range(8)], device="cpu")
    batch.spheres.shape      # (8, Ks, 4) rows [x, y, z, radius]; batch.sphere_mask (8, Ks)
    batch.cover.shape        # (8, Kv, 4) the expert's covering spheres (Scene.expert_objects)
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from vitfly.sim.expert import ExpertObstacles
from vitfly.sim.scenes import Scene


@dataclass(frozen=True, eq=False)
class SceneBatch:
    """E scenes as padded tensors (world frame, m); ``*_mask`` (E, K) bool marks the real rows.

    spheres (E, Ks, 4) [x, y, z, radius]; cylinders (E, Kc, 5) vertical [x, y, z_bottom, z_top,
    radius]; boxes (E, Kb, 6) axis-aligned [x_min, y_min, z_min, x_max, y_max, z_max].
    The privileged expert's view (:class:`vitfly.sim.expert.ExpertObstacles`): cover (E, Kv, 4)
    covering spheres, cover_object (E, Kv) the object of each, anchor_lo / anchor_hi (E, M, 3) the
    box whose nearest point gives object m's distance, object_mask (E, M).
    """

    scenes: tuple[Scene, ...]
    spheres: torch.Tensor
    sphere_mask: torch.Tensor
    cylinders: torch.Tensor
    cylinder_mask: torch.Tensor
    boxes: torch.Tensor
    box_mask: torch.Tensor
    cover: torch.Tensor
    cover_object: torch.Tensor
    cover_mask: torch.Tensor
    anchor_lo: torch.Tensor
    anchor_hi: torch.Tensor
    object_mask: torch.Tensor

    @property
    def num_envs(self) -> int:
        return self.spheres.shape[0]

    @property
    def device(self) -> torch.device:
        return self.spheres.device

    @property
    def dtype(self) -> torch.dtype:
        return self.spheres.dtype

    def replace(self, **changes) -> SceneBatch:
        """A copy with some tensors replaced (e.g. obstacle parameters that require grad)."""
        return dataclasses.replace(self, **changes)


def _pad(arrays: Sequence[np.ndarray], width: int, device, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Stack (K_i, width) arrays into (E, max K_i, width), zero-padded, and the (E, max K_i) mask of real rows."""
    k = max((len(a) for a in arrays), default=0)
    out = np.zeros((len(arrays), k, width), dtype=np.float64)
    mask = np.zeros((len(arrays), k), dtype=bool)
    for i, a in enumerate(arrays):
        out[i, : len(a)] = np.asarray(a, dtype=np.float64).reshape(-1, width)
        mask[i, : len(a)] = True
    return torch.as_tensor(out, dtype=dtype, device=device), torch.as_tensor(mask, device=device)


def scene_batch(
    scenes: Sequence[Scene], device: str | torch.device = "cpu", dtype: torch.dtype = torch.float64,
    spacing_m: float = 0.5,
) -> SceneBatch:
    """Pad ``scenes`` into one :class:`SceneBatch` on ``device``; the expert's cover uses ``spacing_m``
    (as :meth:`vitfly.sim.scenes.Scene.expert_objects`)."""
    scenes = tuple(scenes)
    views = [ExpertObstacles.from_scene(s, spacing_m) for s in scenes]
    spheres, sphere_mask = _pad([s.spheres for s in scenes], 4, device, dtype)
    cylinders, cylinder_mask = _pad([s.cylinders for s in scenes], 5, device, dtype)
    boxes, box_mask = _pad([s.boxes for s in scenes], 6, device, dtype)
    cover, cover_mask = _pad([v.spheres for v in views], 4, device, dtype)
    objects, _ = _pad([v.object_index.astype(np.float64).reshape(-1, 1) for v in views], 1, device, torch.float64)
    anchor_lo, object_mask = _pad([v.anchor_lo for v in views], 3, device, dtype)
    anchor_hi, _ = _pad([v.anchor_hi for v in views], 3, device, dtype)
    return SceneBatch(
        scenes=scenes, spheres=spheres, sphere_mask=sphere_mask, cylinders=cylinders, cylinder_mask=cylinder_mask,
        boxes=boxes, box_mask=box_mask, cover=cover, cover_object=objects[..., 0].long(), cover_mask=cover_mask,
        anchor_lo=anchor_lo, anchor_hi=anchor_hi, object_mask=object_mask,
    )
