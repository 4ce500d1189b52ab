"""What ``--policy`` names for ``vitfly explain``: a checkpoint file, or an architecture with random weights.

- a path: a vitfly/Lightning checkpoint or an original-project state dict (architecture recognised
  from its keys), loaded by ``vitfly.zoo.load_network`` (``torch.load(weights_only=True)``);
- ``random:NAME``: the registered architecture NAME with seeded random weights, labelled
  "(random weights)" everywhere it appears: useful to see the method, meaningless as a finding;
- ``pretrained:NAME``: published pretrained weights (``vitfly.zoo.load_pretrained``).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from vitfly.errors import VitflyError

RANDOM_PREFIX = "random:"


@dataclass
class ExplainedPolicy:
    """A network to explain. label: shown in figures and tables; spec: what the user wrote;
    arch: registry name; random_weights: True for ``random:NAME``."""

    label: str
    spec: str
    net: nn.Module
    arch: str
    random_weights: bool = False


def load_policy(spec: str, label: str | None = None, init_seed: int = 0) -> ExplainedPolicy:
    """One ``--policy`` value as a network in eval mode (VitflyError naming the value if it cannot load)."""
    from vitfly.zoo import create_model, load_network

    if spec.startswith(RANDOM_PREFIX):
        name = spec[len(RANDOM_PREFIX) :]
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(init_seed)
            net = create_model(name).eval()
        return ExplainedPolicy(label or f"{name} (random weights)", spec, net, name, random_weights=True)
    if spec.startswith("pretrained:"):
        from vitfly.zoo.pretrained import load_pretrained, pretrained_name

        name = pretrained_name(spec)
        return ExplainedPolicy(label or name, spec, load_pretrained(name).eval(), name)
    if not Path(spec).is_file():
        raise VitflyError(f"--policy {spec}: no such checkpoint file (or use random:NAME for random weights)")
    net = load_network(spec)
    arch = getattr(net, "model_name", "") or type(net).__name__
    return ExplainedPolicy(label or Path(spec).stem, spec, net, arch)


def load_policies(
    specs: Sequence[str], labels: Sequence[str] | None = None, init_seed: int = 0
) -> list[ExplainedPolicy]:
    """Every ``--policy`` (with optional ``--name`` labels, in order); repeated labels get a suffix."""
    if not specs:
        raise VitflyError("--policy: give at least one checkpoint path or random:NAME")
    labels = list(labels or [])
    if len(labels) > len(specs):
        raise VitflyError(f"--name: {len(labels)} labels for {len(specs)} policies")
    policies = [load_policy(s, labels[i] if i < len(labels) else None, init_seed) for i, s in enumerate(specs)]
    seen: dict[str, int] = {}
    for p in policies:
        n = seen[p.label] = seen.get(p.label, 0) + 1
        if n > 1:
            p.label = f"{p.label} #{n}"
    return policies


def file_stem(label: str) -> str:
    """A label as a file-name stem (letters, digits, '-', '_', '.')."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", label).strip("_") or "policy"
