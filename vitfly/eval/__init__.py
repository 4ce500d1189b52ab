"""Closed-loop evaluation: the paper's metrics, sweeps, reports and plots, findings checked against the paper.

- ``metrics``: the flight metrics as pure functions of one path;
- ``learned_policy``: a zoo network flown as a lockstep simulator policy (paper deployment);
- ``records``: one JSON line per finished trial (crash-safe append, resume, merge);
- ``fingerprint``: what a trial was flown with (policy content, seed, preset, rollout settings) as hashes;
- ``sweep``: trial planning, shards, lockstep batches, worker processes (``vitfly evaluate``);
- ``aggregate``, ``report``, ``plots``, ``wandb_log``: summaries, CSV/Markdown, figures, wandb;
- ``evaluation``: sweep + reports + GIF as one call;
- ``repeats``: repeated trials of one fixed scene from jittered starts, and their mean path;
- ``paper_figures``: the paper's results figures; ``findings``: each paper finding checked, with intervals;
- ``closed_loop``: the closed-loop numbers a weights manifest records, only from trials of those weights;
- ``latency``: the paper's latency table (``vitfly benchmark-latency``);
- ``explain``: attention and Grad-CAM maps over a flight, with consistency numbers (``vitfly explain``).

The end-to-end jobs (``vitfly pipeline``, ``ablate``, ``reproduce``) are in :mod:`vitfly.workflows`.

Submodules are imported on use, so ``import vitfly.eval`` stays light.
"""
