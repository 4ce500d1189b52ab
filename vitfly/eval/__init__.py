"""Closed-loop evaluation: the paper's metrics, sweeps, reports and plots, the main job and the ablation.

- ``metrics``: the flight metrics as pure functions of one path;
- ``learned_policy``: a zoo network flown as a lockstep simulator policy (paper deployment);
- ``records``: one JSON line per finished trial (crash-safe append, resume, merge);
- ``sweep``: trial planning, shards, lockstep batches, worker processes (``vitfly evaluate``);
- ``aggregate``, ``report``, ``plots``, ``wandb_log``: summaries, CSV/Markdown, figures, wandb;
- ``evaluation``: sweep + reports + GIF as one call;
- ``pipeline``: ``vitfly pipeline``, the main job; ``ablation``: ``vitfly ablate --no-state``;
- ``latency``: the paper's latency table (``vitfly benchmark-latency``);
- ``explain``: attention and Grad-CAM maps over a flight, with consistency numbers (``vitfly explain``).

Submodules are imported on use, so ``import vitfly.eval`` stays light.
"""
