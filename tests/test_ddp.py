"""Data-parallel training: the batch sampler's shards, gradient sync under manual TBPTT, `vitfly fit` on 2 gloo ranks.

The DDP runs are real: Lightning's ``ddp_fork`` strategy in this process (two forked CPU ranks) and
``vitfly fit --trainer.strategy ddp --trainer.devices 2 --trainer.accelerator cpu`` in a subprocess, each
rank writing what it saw through ``ddp_probe.SeenBatches``.
"""

from __future__ import annotations

import copy
import csv
import json
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import test_policy_module  # noqa: F401  (registers the tiny BN-free recurrent net "test_recording_lstm")
import torch
from ddp_probe import SeenBatches
from lightning.fabric.utilities.data import _set_sampler_epoch
from test_datamodule import write_dataset
from test_fit_cli import fit_args, run_dir_of

from vitfly.cli import main
from vitfly.datamodules.datamodule import LengthBucketBatchSampler, TrajectoryDataModule
from vitfly.errors import VitflyError
from vitfly.zoo.policy import create_policy

REPO = Path(__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent


def shards(n: int, batch_size: int, world: int, shuffle: bool, seed: int = 0, epoch: int = 0) -> list[list[list[int]]]:
    """Every rank's batches for one epoch."""
    out = []
    for rank in range(world):
        sampler = LengthBucketBatchSampler(
            np.arange(n) % 7 + 1, batch_size, shuffle, seed, pool_batches=2, num_replicas=world, rank=rank
        )
        sampler.set_epoch(epoch)
        batches = list(sampler)
        assert len(batches) == len(sampler)
        out.append(batches)
    return out


def test_unshuffled_shards_by_hand():
    # groups of batch_size x world consecutive items; the last group split evenly, or repeated when too small
    assert shards(5, 2, 2, shuffle=False) == [[[0, 1], [4]], [[2, 3], [4]]]
    assert shards(7, 2, 2, shuffle=False) == [[[0, 1], [4]], [[2, 3], [5, 6]]]
    assert shards(6, 3, 1, shuffle=False) == [[[0, 1, 2], [3, 4, 5]]]


@pytest.mark.parametrize("n", [1, 2, 5, 8, 9, 23, 40, 41])
@pytest.mark.parametrize("batch_size,world", [(1, 2), (2, 2), (3, 2), (2, 3), (4, 4)])
def test_every_rank_gets_the_same_number_of_disjoint_batches(n, batch_size, world):
    per_rank = shards(n, batch_size, world, shuffle=True, seed=3, epoch=2)
    steps = math.ceil(n / (batch_size * world))
    assert all(len(batches) == steps for batches in per_rank)
    items = [i for batches in per_rank for batch in batches for i in batch]
    assert all(0 < len(batch) <= batch_size for batches in per_rank for batch in batches)
    assert set(items) == set(range(n))
    # padding by repeating only when the last group has fewer items than ranks: world - remainder repeats
    remainder = n % (batch_size * world)
    repeats = world - remainder if 0 < remainder < world else 0
    assert len(items) == n + repeats
    # each step's batches are one group of the one-process sampler with batch_size x world
    one = shards(n, batch_size * world, 1, shuffle=True, seed=3, epoch=2)[0]
    for k, group in enumerate(one):
        assert sorted({i for batches in per_rank for i in batches[k]}) == sorted(group)


def test_shards_are_seeded_and_epoch_aware_through_lightnings_set_epoch():
    assert shards(40, 2, 2, shuffle=True, seed=1, epoch=3) == shards(40, 2, 2, shuffle=True, seed=1, epoch=3)
    assert shards(40, 2, 2, shuffle=True, seed=1, epoch=3) != shards(40, 2, 2, shuffle=True, seed=1, epoch=4)
    assert shards(40, 2, 2, shuffle=True, seed=1, epoch=3) != shards(40, 2, 2, shuffle=True, seed=2, epoch=3)
    # Lightning's loops call set_epoch on `batch_sampler.sampler` only: a resumed run's epoch 3 is epoch 3
    sampler = LengthBucketBatchSampler(np.arange(40) % 7 + 1, 2, True, 1, pool_batches=2, num_replicas=2, rank=1)
    loader = torch.utils.data.DataLoader(range(40), batch_sampler=sampler)
    _set_sampler_epoch(loader, 3)
    assert [b.tolist() for b in loader] == shards(40, 2, 2, shuffle=True, seed=1, epoch=3)[1]
    with pytest.raises(VitflyError, match="rank"):
        LengthBucketBatchSampler([1, 2], 1, True, 0, num_replicas=2, rank=2)


def _fit(path, root, devices: int, batch_size: int, module) -> None:
    trainer = L.Trainer(
        max_epochs=2,
        default_root_dir=root,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        accelerator="cpu",
        devices=devices,
        strategy="ddp_fork" if devices > 1 else "auto",
        use_distributed_sampler=False,
        callbacks=[SeenBatches()],
    )
    trainer.fit(module, datamodule=TrajectoryDataModule(path, batch_size=batch_size, val_fraction=0.0))


def test_ddp_manual_tbptt_equals_one_process_with_the_union_batch(tmp_path):
    """2 ranks x 2 trajectories train exactly as 1 process x 4 (a net without batch norm): gradients all-reduced
    in every backward, ranks with fewer TBPTT chunks joining with zero gradients, losses weighted by valid steps."""
    path = write_dataset(tmp_path / "d.h5", [5, 23, 9, 14, 3, 17, 8, 11])  # 1 to 6 chunks of 4 steps
    torch.manual_seed(0)
    ddp = create_policy("test_recording_lstm", tbptt_steps=4, warmup_epochs=0, lr=1e-2)
    one, start = copy.deepcopy(ddp), copy.deepcopy(ddp.state_dict())
    _fit(path, tmp_path / "ddp", 2, 2, ddp)  # Lightning loads rank 0's weights back into `ddp`
    _fit(path, tmp_path / "one", 1, 4, one)
    for key, value in one.state_dict().items():
        assert not torch.equal(value, start[key])  # it trained
        torch.testing.assert_close(ddp.state_dict()[key], value, rtol=1e-5, atol=1e-6)
    seen = [json.loads((tmp_path / "ddp" / f"seen_rank{r}.json").read_text()) for r in range(2)]
    single = json.loads((tmp_path / "one" / "seen_rank0.json").read_text())
    chunks = [[math.ceil(max(b["lengths"]) / 4) for b in s["batches"]] for s in seen]
    assert chunks[0] != chunks[1]  # the ranks' chunk counts differ: the zero-gradient steps were taken
    # both ranks stepped as often as the rank with more chunks, which is what the one process did
    expected = np.cumsum([sum(np.maximum(*chunks)[e * 2 : e * 2 + 2]) for e in range(2)]).tolist()
    assert seen[0]["steps_after_epoch"] == seen[1]["steps_after_epoch"] == expected == single["steps_after_epoch"]


def _run(args: list[str], timeout_s: float) -> subprocess.CompletedProcess:
    """`python -m vitfly.cli ARGS` in its own process group, killed whole (both ranks) if it overruns."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), str(TESTS)]), "WANDB_MODE": "offline"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "vitfly.cli", *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    try:
        out, _ = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
        pytest.fail(f"vitfly fit with DDP still running after {timeout_s} s (hung?):\n{out[-3000:]}")
    return subprocess.CompletedProcess(proc.args, proc.returncode, out)


def test_vitfly_fit_ddp_on_two_cpu_ranks_trains_each_rank_on_its_own_half(tmp_path):
    # lengths 9..12 with 4-step chunks: every batch is 3 optimiser steps (ceil(L / 4) = 3 for 9 <= L <= 12)
    data = write_dataset(tmp_path / "d.h5", [9, 12, 10, 11, 9, 12, 10, 11, 10, 12])
    # 2 of the 10 trajectories held out, whatever the shipped recipe's val_fraction; no mirroring (the probe
    # compares the trajectories each rank saw)
    probe = ["--model.init_args.tbptt_steps", "4", "--data.val_fraction", "0.2", "--data.mirror_prob", "0.0",
             "--trainer.callbacks+=ddp_probe.SeenBatches"]
    ddp_args = fit_args(data, tmp_path / "ddp", *probe, "--trainer.strategy", "ddp", "--trainer.devices", "2",
                        "--trainer.accelerator", "cpu")  # fmt: skip
    done = _run(ddp_args, timeout_s=300)  # about 20 s on a quiet 2-core machine
    assert done.returncode == 0, done.stdout[-3000:]
    assert main(fit_args(data, tmp_path / "one", *probe)) == 0

    # one run directory, written by rank 0 (rank 1 adds only its probe file)
    (run,) = (tmp_path / "ddp").iterdir()
    files = {str(p.relative_to(run)) for p in run.rglob("*") if p.is_file()}
    assert files == {"checkpoints/best.ckpt", "checkpoints/last.ckpt", "metrics.csv", "split.json", "config.yaml",
                     "hparams.yaml", "seen_rank0.json", "seen_rank1.json"}  # fmt: skip
    one_run = run_dir_of(tmp_path / "one")
    split = json.loads((run / "split.json").read_text())
    assert split == json.loads((one_run / "split.json").read_text())
    assert len(split["train"]) == 8 and len(split["val"]) == 2

    seen = [json.loads((run / f"seen_rank{r}.json").read_text())["batches"] for r in range(2)]
    single = json.loads((one_run / "seen_rank0.json").read_text())["batches"]
    for epoch in range(2):
        for stage, everything in (("train", split["train"]), ("val", split["val"])):
            mine = [[t for b in s if (b["stage"], b["epoch"]) == (stage, epoch) for t in b["traj"]] for s in seen]
            assert not set(mine[0]) & set(mine[1])  # disjoint halves
            assert sorted(mine[0] + mine[1]) == sorted(everything)  # together: every trajectory once
            assert len(mine[0]) == len(mine[1]) == len(everything) // 2
        batches = [[b for b in s if (b["stage"], b["epoch"]) == ("train", epoch)] for s in (*seen, single)]
        assert len(batches[0]) == len(batches[1]) == len(batches[2]) // 2 == 2
    epoch_sets = [{t for b in seen[0] if (b["stage"], b["epoch"]) == ("train", e) for t in b["traj"]} for e in (0, 1)]
    assert epoch_sets[0] != epoch_sets[1]  # each epoch deals the trajectories out anew

    # half the optimiser steps per epoch: 2 batches x 3 chunks per rank against 4 x 3 in one process
    ddp_steps = [json.loads((run / f"seen_rank{r}.json").read_text())["steps_after_epoch"] for r in range(2)]
    one_steps = json.loads((one_run / "seen_rank0.json").read_text())["steps_after_epoch"]
    assert ddp_steps[0] == ddp_steps[1] == [6, 12] and one_steps == [12, 24]
    assert torch.load(run / "checkpoints/last.ckpt", weights_only=True)["global_step"] == 12

    # val/loss was reduced over both ranks' halves: one process validating the same checkpoint agrees
    with open(run / "metrics.csv") as fh:
        logged = [float(r["val/loss"]) for r in csv.DictReader(fh) if r["val/loss"]][-1]
    check = tmp_path / "check"
    assert main(["validate", *fit_args(data, check, "--ckpt_path", str(run / "checkpoints/last.ckpt"))[1:]]) == 0
    with open(run_dir_of(check) / "metrics.csv") as fh:
        (row,) = list(csv.DictReader(fh))
    assert float(row["val/loss"]) == pytest.approx(logged, rel=1e-5)


def test_ddp_trainer_config_composes_after_a_model_config(capsys):
    args = ["fit", "--config", str(REPO / "configs/fit/vit_lstm.yaml"), "--config",
            str(REPO / "configs/fit/trainer/ddp.yaml"), "--print_config"]  # fmt: skip
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "strategy: ddp" in out and "accelerator: gpu" in out and "devices: -1" in out
    assert "use_distributed_sampler: false" in out and "lr: 0.0001" in out
    # without it the CLI's default already keeps Lightning from injecting a DistributedSampler
    assert main(["fit", "--config", str(REPO / "configs/fit/convnet.yaml"), "--print_config"]) == 0
    assert "use_distributed_sampler: false" in capsys.readouterr().out
