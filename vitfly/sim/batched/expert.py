"""The privileged expert of :mod:`vitfly.sim.expert` for E scenes at once (torch).

The same inputs and choices: the ``max_obstacles`` scene objects nearest the drone within
``max_range_m`` (a tree counts once; ties in distance keep the scene order), of their covering spheres
those 0 < dx < ``lookahead_m`` ahead, the 33 x 33 waypoint grid in the plane 8 m ahead, each
waypoint blocked when the infinite line through the drone and it passes within radius + 0.6 m of a
centre, the free waypoint nearest the grid centre (Manhattan distance, ties to the first in row-major
order), command = unit(waypoint) * desired speed, the fallback (0.5, 0, 0.25) when every waypoint is
blocked, then the altitude floor and the take-off ramp.

Like the numpy expert it tests the waypoints nearest the centre first (the first 64 in search order)
and the rest only for the scenes that need them, in chunks that bound the (scenes x lines x spheres)
working set.

Example::

    commands = expert_commands(position, speeds, batch)   # (E, 3) m/s, world frame
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache

import numpy as np
import torch

from vitfly.sim.batched.scenes import SceneBatch
from vitfly.sim.expert import ExpertConfig, _search_order, _unit_directions, waypoint_grid

# largest (scenes x lines x spheres) block of the blocked-line test held at once (elements)
BLOCK_ELEMENTS = 1 << 23


def visible_cover(position: torch.Tensor, batch: SceneBatch, config: ExpertConfig) -> torch.Tensor:
    """(E, Kv) bool: the covering spheres of the objects Flightmare would have published to the expert.

    The ``max_obstacles`` objects nearest ``position`` (E, 3) m among those within ``max_range_m``
    (distance to each object's anchor box, <= the range); ties in distance keep the scene order.
    """
    n_max, rng = config.max_obstacles, config.max_range_m
    if n_max is None and rng is None:
        return batch.cover_mask
    p = position[:, None, :]
    delta = torch.minimum(torch.maximum(p, batch.anchor_lo), batch.anchor_hi) - p
    dist2 = (delta * delta).sum(-1)
    chosen = batch.object_mask
    if rng is not None:
        chosen = chosen & (dist2 <= rng * rng)
    if n_max is not None and chosen.shape[1] > n_max:
        # the n_max nearest chosen, ties at the cut in scene order (what a stable sort would keep),
        # from the n_max-th smallest distance: no full sort
        dist2 = torch.where(chosen, dist2, torch.inf)
        cut = torch.topk(dist2, n_max, dim=1, largest=False, sorted=False).values.amax(1, keepdim=True)
        below, tie = chosen & (dist2 < cut), chosen & (dist2 == cut)
        chosen = below | (tie & (torch.cumsum(tie, 1) <= n_max - below.sum(1, keepdim=True)))
    return torch.gather(chosen, 1, batch.cover_object) & batch.cover_mask


def _compact(mask: torch.Tensor, *values: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Move each row's selected entries to the front: (mask', values'...) of width max(row count)."""
    width = int(mask.sum(1).max()) if mask.numel() else 0
    order = torch.sort(mask.to(torch.int8), dim=1, descending=True, stable=True).indices[:, :width]
    return (torch.gather(mask, 1, order), *(torch.gather(v, 1, order[..., None].expand(-1, -1, v.shape[-1]))
                                            for v in values))


def blocked_lines(directions: torch.Tensor, centres: torch.Tensor, radius2: torch.Tensor) -> torch.Tensor:
    """(E, L) bool: line l (unit direction, (L, 3) or (E, L, 3)) passes within sqrt(radius2) (E, K) of a
    centre (E, K, 3) (relative to the drone); padded spheres carry radius2 = -1 and block nothing."""
    along = directions @ centres.transpose(1, 2) if directions.dim() == 3 else torch.einsum(
        "lj,ekj->elk", directions, centres)
    dist2 = (centres * centres).sum(-1)[:, None, :] - along * along  # squared distance centre-line
    return (dist2 <= radius2[:, None, :]).any(-1)


@lru_cache(maxsize=8)
def _grid_tensors(config: ExpertConfig, device: str, dtype: torch.dtype):
    """Unit directions in search order (head, tail) and the waypoints in search order (G G, 3)."""
    head, tail = _search_order(config)
    order = np.concatenate([head, tail])
    dirs = torch.as_tensor(_unit_directions(config)[order], dtype=dtype, device=device)
    wpts = torch.as_tensor(waypoint_grid(config)[0].reshape(-1, 3)[order], dtype=dtype, device=device)
    return dirs, wpts, len(head)


def first_free(rel: torch.Tensor, radius2: torch.Tensor, config: ExpertConfig,
               blocked: Callable = blocked_lines) -> tuple[torch.Tensor, torch.Tensor]:
    """Position in the search order of the free waypoint nearest the grid centre, and whether there is one.

    rel (E, K, 3) obstacle centres relative to the drone, radius2 (E, K) squared inflated radii (-1 on
    padding). Returns ``(index (E,) long, found (E,) bool)``.
    """
    e = rel.shape[0]
    dirs, _, n_head = _grid_tensors(config, str(rel.device), rel.dtype)
    index = torch.zeros(e, dtype=torch.long, device=rel.device)
    found = torch.zeros(e, dtype=torch.bool, device=rel.device)
    if rel.shape[1] == 0:  # nothing ahead: the centre waypoint is free everywhere
        return index, torch.ones_like(found)
    k = rel.shape[1]
    todo = torch.arange(e, device=rel.device)
    for offset, lines in ((0, dirs[:n_head]), (n_head, dirs[n_head:])):
        if len(todo) == 0:
            break
        chunk = max(1, BLOCK_ELEMENTS // (len(lines) * k))
        for start in range(0, len(todo), chunk):
            rows = todo[start : start + chunk]
            free = ~blocked(lines, rel[rows], radius2[rows])
            has = free.any(1)
            index[rows] = torch.where(has & ~found[rows], offset + free.to(torch.int8).argmax(1), index[rows])
            found[rows] = found[rows] | has
        todo = todo[~found[todo]]
    return index, found


def obstacles_ahead(position: torch.Tensor, batch: SceneBatch, config: ExpertConfig):
    """``(keep (E, Kv) bool, rel (E, Kv, 3) m, radii (E, Kv) m)``: the visible covering spheres that may block
    a waypoint line (0 < dx < lookahead, near the lines' double pyramid), their centres relative to the
    drone at ``position`` (E, 3) m and their inflated radii."""
    visible = visible_cover(position, batch, config)
    rel = batch.cover[..., :3] - position[:, None, :]
    radii = batch.cover[..., 3] + config.inflate_m
    # lines lie in the double pyramid |y|, |z| <= slope x: spheres farther than their inflated radius
    # from its side planes block none of them (the numpy expert's shortcut, same answer)
    slope = config.grid_half_extent_m / config.lookahead_m
    margin = radii * (1.0 + slope * slope) ** 0.5
    dx = rel[..., 0]
    near_cone = (rel[..., 1].abs() - slope * dx < margin) & (rel[..., 2].abs() - slope * dx < margin)
    return visible & (dx > 0.0) & (dx < config.lookahead_m) & near_cone, rel, radii


def expert_commands(position: torch.Tensor, desired_speed: torch.Tensor, batch: SceneBatch,
                    config: ExpertConfig | None = None, blocked: Callable = blocked_lines,
                    ahead: Callable = obstacles_ahead) -> torch.Tensor:
    """World-frame velocity commands (E, 3) m/s for drones at ``position`` (E, 3) m flying at
    ``desired_speed`` (E,) m/s (see the module docstring). ``blocked`` and ``ahead`` stand in for
    :func:`blocked_lines` and :func:`obstacles_ahead` (their compiled twins, say)."""
    cfg = config or ExpertConfig()
    with torch.no_grad():
        keep, rel, radii = ahead(position, batch, cfg)
        keep, rel, radii = _compact(keep, rel, radii[..., None])
        radius2 = torch.where(keep, radii[..., 0] * radii[..., 0], -torch.ones_like(radii[..., 0]))
        index, found = first_free(rel, radius2, cfg, blocked)
        _, wpts, _ = _grid_tensors(cfg, str(position.device), position.dtype)
        wpt = wpts[index]
        speed = desired_speed.to(position.dtype)
        command = wpt / torch.linalg.vector_norm(wpt, dim=-1, keepdim=True) * speed[:, None]
        command = torch.where(found[:, None], command, command.new_tensor(cfg.fallback_command))
        x, z = position[:, 0], position[:, 2]
        vz = torch.where(z < cfg.min_altitude_m, cfg.altitude_gain * (cfg.min_altitude_m - z), command[:, 2])
        vx = takeoff_ramp(command[:, 0], x, speed, cfg)
        return torch.stack([vx, command[:, 1], vz], -1)


def takeoff_ramp(vx_mps: torch.Tensor, x_m: torch.Tensor, desired_speed_mps: torch.Tensor,
                 config: ExpertConfig | None = None) -> torch.Tensor:
    """:func:`vitfly.sim.expert.takeoff_ramp` on tensors: while x < 2 m, vx = max(1, x / 2 * desired speed)."""
    cfg = config or ExpertConfig()
    ramp = torch.clamp(x_m / cfg.ramp_distance_m * desired_speed_mps, min=cfg.ramp_min_speed_mps)
    return torch.where(x_m < cfg.ramp_distance_m, ramp, vx_mps)
