"""Contact between each drone and its scene's obstacles, for E scenes at once (torch).

The tests of :mod:`vitfly.sim.collision`: signed distances from the drone's centre to spheres, finite
vertical cylinders and axis-aligned boxes (negative inside), contact when one is below the body radius
(0: a point drone, strictly inside, as the paper's evaluator). The rollout keeps, once per control tick,
the obstacles the drone can reach before the next tick (:func:`nearby`), and tests only those at every
physics step, as the numpy engine does.

Example::

    d = signed_distances(position, batch)          # (E, Ks + Kc + Kb), +inf on padded rows
    touching = in_contact(position, batch, d < 1.0, body_radius_m=0.0)   # (E,) bool
"""

from __future__ import annotations

import torch

from vitfly.sim.batched.scenes import SceneBatch


def _outside_or_inside(excess: list[torch.Tensor]) -> torch.Tensor:
    """Signed distance from per-axis excesses (m): the norm of the positive parts outside, the largest inside."""
    outside = torch.stack(excess, -1).clamp(min=0.0)
    out = torch.sqrt((outside * outside).sum(-1))
    inside = torch.stack(excess, -1).amax(-1)
    return torch.where(out > 0, out, inside)


def signed_distances(position: torch.Tensor, batch: SceneBatch) -> torch.Tensor:
    """(E, Ks + Kc + Kb) signed distance (m) from ``position`` (E, 3) to each obstacle; +inf on padding.

    Order: spheres, cylinders, boxes (as in each scene), each padded to the batch's widest.
    """
    p = position[:, None, :]
    inf = torch.tensor(float("inf"), dtype=position.dtype, device=position.device)
    sph = batch.spheres
    rel = sph[..., :3] - p
    d_sph = torch.sqrt((rel * rel).sum(-1)) - sph[..., 3]
    cyl = batch.cylinders
    radial = torch.hypot(cyl[..., 0] - p[..., 0], cyl[..., 1] - p[..., 1]) - cyl[..., 4]
    axial = torch.maximum(cyl[..., 2] - p[..., 2], p[..., 2] - cyl[..., 3])
    # a finite cylinder: hypot of the positive parts outside, the larger excess inside
    outside = torch.hypot(radial.clamp(min=0.0), axial.clamp(min=0.0))
    d_cyl = torch.where((radial > 0) | (axial > 0), outside, torch.maximum(radial, axial))
    box = batch.boxes
    excess = torch.maximum(box[..., :3] - p, p - box[..., 3:])
    d_box = _outside_or_inside(list(excess.unbind(-1)))
    return torch.cat([
        torch.where(batch.sphere_mask, d_sph, inf),
        torch.where(batch.cylinder_mask, d_cyl, inf),
        torch.where(batch.box_mask, d_box, inf),
    ], 1)  # fmt: skip


def nearby(position: torch.Tensor, batch: SceneBatch, horizon_m: torch.Tensor, body_radius_m: float) -> torch.Tensor:
    """(E, K) bool: the obstacles the drone centre could touch after moving at most ``horizon_m`` (E,) m
    (as :meth:`vitfly.sim.collision.ContactChecker.nearby`)."""
    return signed_distances(position, batch) < (body_radius_m + horizon_m)[:, None]


def in_contact(
    position: torch.Tensor, batch: SceneBatch, candidates: torch.Tensor, body_radius_m: float
) -> torch.Tensor:
    """(E,) bool: the drone at ``position`` (E, 3) touches one of its ``candidates`` (E, K) obstacles."""
    return ((signed_distances(position, batch) < body_radius_m) & candidates).any(1)
