"""End-to-end jobs that compose the rest of vitfly: collect, train, evaluate, report.

- :mod:`vitfly.workflows.pipeline`: the quick start (``vitfly pipeline``).
- :mod:`vitfly.workflows.ablation`: the paper's no-state ablation (``vitfly ablate``).

Workflows sit above :mod:`vitfly.eval`, :mod:`vitfly.training` and :mod:`vitfly.sim.collect` and import
them; nothing below imports a workflow.
"""
