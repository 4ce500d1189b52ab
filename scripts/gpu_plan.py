"""The next GPU slot of a reproduce preset, as docs/reproduce.md plans them: which unfinished runs it carries and
which runs it starts (``scripts/gpu.py status`` prints it, ``scripts/gpu.py carry`` writes the carry).

What a slot does not finish comes home as a resume state, and the next slot must carry it back: the device tool
sends the working tree, carry/ and .whl/, 64 MiB in all. Travelling light (``scripts/gpu_travel.py``) the tree is
2.1 MiB without carry/: the shipped weights, the docs and the carried runs that do not go to this slot (trained on
a CPU, or finished) stay here, so the carry holds what the rest leaves. A carried state is lean
(``scripts/gpu_carry.py``): last.* (fp32 weights and Adam's moments, in fp32 where they fit, else in bf16: an
inexact resume; squeezed losslessly, ``scripts/gpu_squeeze.py``), and best.* only where the preset flies the best
epoch (fp16 from a slot, fp32 for runs of ``train.cpu_models``). So a slot carries the unfinished runs
(``train.slot_order`` first) within that room, as many as fit in bf16 and then fp32 for those the room still holds,
and starts runs not started yet, in the same order, only while the states expected home still fit it: a carried run
that will not finish in this slot (its last slot's epoch time says so) counts with its size, a new run with its
state's size estimated from its parameter count. A run whose state could never travel (ResNet-18's) starts only
alone, and must finish inside the command. Runs of ``train.cpu_models`` train on a CPU and are left out, as are
runs being trained here (``vitfly reproduce`` resumes them; ``status`` leaves out a run a process here trains now,
``RunState.here_now``)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

# a carried state: last.*'s fp32 weights and Adam's two moments per parameter (best.* adds BEST_BYTES_PER_PARAM)
STATE_BYTES_PER_PARAM = {"fp32": 4 + 2 * 4, "bf16": 4 + 2 * 2}
# last.* travels squeezed (scripts/gpu_squeeze.py): measured 0.818-0.829 of its bytes with fp32 moments and
# 0.734-0.749 with bf16 (ViT+LSTM after 7 epochs, LSTMnet and ConvNet after 100); planned with 3 points to spare
SQUEEZED = {"fp32": 0.85, "bf16": 0.78}
BEST_BYTES_PER_PARAM = {"slot": 2, "cpu": 4}  # best.* as trained: fp16 from a slot, fp32 from a CPU run
FOLDER_BYTES = 192 * 1024  # the rest of a run folder: checkpoint headers, metrics, split, marker (0.1-0.2 MiB
# above the tensors, benchmarks/resume_state_size.py)
MOMENTS = {"auto": ("fp32", "bf16"), "fp32": ("fp32",), "bf16": ("bf16",)}  # what a carry may use, best first
STARTUP_S = 60.0  # before the first epoch: the data collected (about 25 s for 588 flights) and the runs started


@dataclass
class RunState:
    """One run of the preset as it stands here."""

    run: object  # vitfly.workflows.reproduce_config.Run
    state: str  # done, unfinished, started here, not started
    text: str  # what `status` prints after the label
    folder: Path | None = None  # an unfinished run's folder (what the device tool carries)
    size: int = 0  # its bytes
    marker: dict = field(default_factory=dict)  # an unfinished run's resume marker (epochs, max_epochs, epoch_s)
    here_now: bool = False  # a process here trains it now (vitfly reproduce): no slot takes it

    @property
    def label(self) -> str:
        return self.run.dir_name


@dataclass
class Slot:
    """The next slot: what it carries and starts, what waits, and what is left to a CPU."""

    carry: list[RunState] = field(default_factory=list)
    start: list[RunState] = field(default_factory=list)
    no_room: list[str] = field(default_factory=list)  # unfinished runs beyond this call's carry
    wait: dict[str, str] = field(default_factory=dict)  # runs not started: label -> why not in this slot
    on_cpu: list[RunState] = field(default_factory=list)
    back_bytes: int = 0  # resume states expected home
    alone: str | None = None  # a run whose state cannot travel: it must finish inside the command
    moments: dict[str, str] = field(default_factory=dict)  # carried label -> the precision its moments travel in
    sizes: dict[str, int] = field(default_factory=dict)  # carried label -> its carried bytes (estimated)


def slot_rank(cfg, run) -> tuple:
    """Slot order: runs with the state, then without, then draws; within each, ``train.slot_order`` and then
    the order of ``train.models``."""
    t = cfg.train
    order = list(dict.fromkeys([*t.slot_order, *t.models]))
    return (run.seed is not None, not run.use_state, order.index(run.model), run.seed or 0)


def parameters(cfg, run) -> int:
    """The parameter count of ``run``'s network, as its recipe builds it."""
    from vitfly.workflows.reproduce_config import train_stage
    from vitfly.zoo.registry import create_model

    kwargs = train_stage(cfg, run.model, run.use_state, seed=run.seed).policy_kwargs.get("model_kwargs") or {}
    return sum(p.numel() for p in create_model(run.model, use_state=run.use_state, **kwargs).parameters())


def max_epochs(cfg, run) -> int:
    from vitfly.workflows.reproduce_config import train_stage

    return train_stage(cfg, run.model, run.use_state, seed=run.seed).max_epochs


def state_bytes(cfg, run, moments: str) -> int:
    """The carried resume state of ``run``, estimated from its network's parameter count: last.* squeezed and,
    where the preset flies the best epoch (``select: best``), best.* as trained: fp16 from a slot, fp32 for a run
    of ``train.cpu_models`` (``scripts/gpu_carry.py``)."""
    from scripts.gpu_preset import flies_best

    n = parameters(cfg, run)
    best = BEST_BYTES_PER_PARAM["cpu" if run.model in cfg.train.cpu_models else "slot"] * flies_best(cfg, run)
    return int(n * STATE_BYTES_PER_PARAM[moments] * SQUEEZED[moments]) + n * best + FOLDER_BYTES


def epochs_per_slot(marker: dict, train_s: float) -> int | None:
    """Epochs that fit ``train_s`` at an unfinished run's last slot's epoch times: the first (compilation and
    CUDA-graph capture) and the steady ones after it; None before any was measured."""
    epoch_s = marker.get("epoch_s")
    if not epoch_s:
        return None
    first = marker.get("first_epoch_s", epoch_s)
    return 0 if first > train_s else 1 + int((train_s - first) // epoch_s)


def finishes(r: RunState, train_s: float) -> bool:
    """Whether an unfinished run's remaining epochs fit ``train_s``."""
    per_slot = epochs_per_slot(r.marker, train_s)
    left = r.marker.get("max_epochs", 0) - r.marker.get("epochs", 0)
    return per_slot is not None and 0 < left <= per_slot


def carried_moments(r: RunState, moments: str) -> tuple[str, ...]:
    """The precisions an unfinished run's moments may travel in, best first: bf16 alone for a run restored from
    a carry in bf16 (its moments are bf16's values already: fp32 would carry them no better)."""
    return ("bf16",) if r.marker.get("carried_moments") == "bf16" else MOMENTS[moments]


def next_slot(cfg, rows: list[RunState], carry_bytes: int, moments: str = "auto",
              deadline_s: float = 560.0, reserve_s: float = 40.0) -> Slot:
    """The next slot for the runs ``rows`` (every run of the preset, as ``run_states`` lists them); ``carry_bytes``:
    the room a call leaves the carry (the carried runs of no slot stay here: ``scripts/gpu_travel.py``);
    ``moments``: what the carried moments may be (auto: fp32 where they fit)."""
    from scripts.gpu_slots import mib

    slot = Slot()
    cpu = set(cfg.train.cpu_models)
    train_s = deadline_s - reserve_s - STARTUP_S
    # which unfinished runs travel, each in its smallest precision, in slot order; then, in the same order, exact
    # (fp32) moments where the room still holds them: a second run carried beats the first carried exactly
    carried = 0
    for r in sorted((r for r in rows if r.state == "unfinished"), key=lambda r: slot_rank(cfg, r.run)):
        smallest = carried_moments(r, moments)[-1]
        size = state_bytes(cfg, r.run, smallest)
        if carried + size > carry_bytes:
            slot.no_room.append(r.label)
            continue
        slot.carry.append(r)
        slot.moments[r.label], slot.sizes[r.label] = smallest, size
        carried += size
        slot.back_bytes += 0 if finishes(r, train_s) else state_bytes(cfg, r.run, MOMENTS[moments][-1])
    for r in slot.carry:
        best = next(m for m in carried_moments(r, moments)
                    if carried - slot.sizes[r.label] + state_bytes(cfg, r.run, m) <= carry_bytes)
        carried += state_bytes(cfg, r.run, best) - slot.sizes[r.label]
        slot.moments[r.label], slot.sizes[r.label] = best, state_bytes(cfg, r.run, best)
    for r in sorted((r for r in rows if r.state == "not started"), key=lambda r: slot_rank(cfg, r.run)):
        if r.run.model in cpu:
            slot.on_cpu.append(r)
            continue
        size = state_bytes(cfg, r.run, MOMENTS[moments][-1])  # the next carry may shrink its moments
        if size > carry_bytes:  # it cannot come back unfinished: alone, with the whole command
            if not slot.carry and not slot.start:
                slot.start.append(r)
                slot.alone = f"{r.label}'s state ({mib(size)}) cannot travel: it must finish inside this command"
                break
            slot.wait[r.label] = f"state {mib(size)}: cannot travel, trains alone in a slot"
        elif slot.back_bytes + size <= carry_bytes:
            slot.start.append(r)
            slot.back_bytes += size
        else:
            slot.wait[r.label] = f"state {mib(size)}: would not fit the next carry"
    for r in rows:  # left behind by a run that trains alone
        if r.state == "not started" and r.run.model not in cpu and r not in slot.start:
            slot.wait.setdefault(r.label, "a later slot")
    return slot


def slot_after(cfg, rows: list[RunState], slot: Slot, carry_bytes: int, moments: str = "auto",
               deadline_s: float = 560.0, reserve_s: float = 40.0) -> Slot | None:
    """What a follow-on call starts should every run of ``slot`` finish inside the first call (the vitfly arm's
    large batches may: ViT+LSTM's 100 epochs take about 5 minutes of an H100): the next slot with them done.
    None where that cannot be: a carried run that its last slot's epoch time says will not finish, or a run that
    trains alone."""
    train_s = deadline_s - reserve_s - STARTUP_S
    if slot.alone or not (slot.carry or slot.start) or not all(finishes(r, train_s) for r in slot.carry):
        return None
    ran = {r.label for r in [*slot.carry, *slot.start]}
    after = next_slot(cfg, [replace(r, state="done") if r.label in ran else r for r in rows], carry_bytes, moments,
                      deadline_s, reserve_s)
    return after if after.start and not after.alone else None
