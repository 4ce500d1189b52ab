"""End-to-end jobs that compose the rest of vitfly: collect, train, evaluate, report.

- :mod:`vitfly.workflows.pipeline`: the quick start (``vitfly pipeline``).
- :mod:`vitfly.workflows.ablation`: the paper's no-state ablation (``vitfly ablate``).
- :mod:`vitfly.workflows.reproduce`: the paper's whole results section (``vitfly reproduce``), configured by
  :mod:`~vitfly.workflows.reproduce_config`, reported by :mod:`~vitfly.workflows.reproduce_report`.
- :mod:`vitfly.workflows.dagger`: DAgger with the privileged expert against behaviour cloning at equal labelled
  frames (``vitfly dagger``), configured by :mod:`~vitfly.workflows.dagger_config`, its stages planned and
  recorded by :mod:`~vitfly.workflows.dagger_stages`, reported by :mod:`~vitfly.workflows.dagger_report`.
- :mod:`vitfly.workflows.closed_loop_check`: a training callback that flies held-out scenes every N epochs.

Workflows sit above :mod:`vitfly.eval`, :mod:`vitfly.training` and :mod:`vitfly.sim.collect` and import
them; nothing below imports a workflow.
"""
