"""Numbers for the paper's qualitative claim ("diffuse and unstable" vs "consistently on obstacle edges").

- temporal consistency: the Pearson correlation of consecutive maps (t, t + 1) over the 60 x 90
  pixels, averaged over the trial; pairs where either map is constant have no correlation and are left
  out (and counted);
- edge mass share: the share of a map's mass on obstacle-edge pixels, averaged over the ticks with
  any edge in view and any mass; beside it the edge area share (the share of pixels that are edges,
  over the same ticks: what a uniform map would score) and their ratio, the edge lift (1 = no
  preference for edges).
"""

from __future__ import annotations

import numpy as np


def consecutive_correlations(maps: np.ndarray) -> np.ndarray:
    """(T - 1,) Pearson correlation of maps t and t + 1 (maps (T, H, W)); NaN where either is constant."""
    flat = np.asarray(maps, dtype=np.float64).reshape(len(maps), -1)
    centred = flat - flat.mean(axis=1, keepdims=True)
    norm = np.linalg.norm(centred, axis=1)
    varies = (flat.max(axis=1) - flat.min(axis=1)) > 1e-9 * np.abs(flat).max(axis=1)  # all-zero maps: False
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = np.einsum("ij,ij->i", centred[:-1], centred[1:]) / (norm[:-1] * norm[1:])
    corr[~(varies[:-1] & varies[1:])] = np.nan
    return corr


def temporal_consistency(maps: np.ndarray) -> dict:
    """{"consistency": mean correlation of consecutive maps (NaN if none), "consistency_pairs": pairs used}."""
    corr = consecutive_correlations(maps) if len(maps) > 1 else np.zeros(0)
    valid = corr[np.isfinite(corr)]
    return {"consistency": float(valid.mean()) if len(valid) else float("nan"), "consistency_pairs": int(len(valid))}


def edge_mass_share(maps: np.ndarray, edges: np.ndarray) -> dict:
    """Share of map mass on edge pixels (maps (T, H, W) >= 0, edges (T, H, W) bool), see the module doc."""
    m = np.asarray(maps, dtype=np.float64).reshape(len(maps), -1)
    e = np.asarray(edges, dtype=bool).reshape(len(edges), -1)
    total = m.sum(axis=1)
    use = (total > 0) & e.any(axis=1)
    if not use.any():
        nan = float("nan")
        return {"edge_mass_share": nan, "edge_area_share": nan, "edge_lift": nan, "edge_ticks": 0}
    mass = ((m * e).sum(axis=1)[use] / total[use]).mean()
    area = e[use].mean(axis=1).mean()
    return {"edge_mass_share": float(mass), "edge_area_share": float(area), "edge_lift": float(mass / area),
            "edge_ticks": int(use.sum())}


def map_metrics(maps: np.ndarray, edges: np.ndarray | None) -> dict:
    """Temporal consistency and (with edges) the edge mass share of one map kind over one trial."""
    out = temporal_consistency(maps)
    if edges is not None:
        out.update(edge_mass_share(maps, edges))
    return out
