"""scripts/gpu_plan.py: the next GPU slot of the paper presets, worked out by hand.

A carried resume state of the paper presets is last.* alone (the paper arm flies its last epoch, so it keeps no
best one; the vitfly arm's best.* would add 2 bytes a parameter): 12 bytes a parameter with fp32 Adam moments
(fp32 weights 4 + two moments 8) and 8 with bf16 moments, squeezed to 0.85 and 0.78 of that (the plan's margin
over the measured 0.82 and 0.74, scripts/gpu_squeeze.py), plus 192 KiB for the rest of the run folder
(checkpoint headers, metrics); the parameter counts are the ones the recipes state (configs/fit/paper/*.yaml):
ViT+LSTM 3,563,663 (36,545,970 bytes with fp32 moments, 22,433,865 with bf16), ViT 3,101,199 (31,828,837 and
19,548,089), UNet+LSTM 2,955,822 (-, 18,640,937), LSTMnet 2,949,937 (-, 18,604,214). A call
carries 64 MiB with the working tree (30.7 MiB, 2026-11-28) and .whl/, so the room here is 32 MiB =
33,554,432 bytes.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import pytest

from vitfly.errors import VitflyError
from vitfly.workflows.reproduce_config import load_reproduce_config, runs

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from scripts.gpu_plan import RunState, next_slot, slot_after, state_bytes  # noqa: E402

ROOM = 32 * 2**20  # what the working tree and .whl/ leave a call's carry


def preset(name: str, **train):
    return load_reproduce_config(REPO / "configs" / "reproduce.yaml", name, {"train": train} if train else None)


def rows(cfg, done=(), unfinished=None) -> list[RunState]:
    """Every run of ``cfg``: ``done`` labels done, ``unfinished`` label -> (bytes, marker), the rest not started."""
    unfinished = unfinished or {}
    out = []
    for run in runs(cfg):
        label = run.dir_name
        if label in done:
            out.append(RunState(run, "done", "done"))
        elif label in unfinished:
            size, marker = unfinished[label]
            out.append(RunState(run, "unfinished", "unfinished", Path("runs") / label, size, marker))
        else:
            out.append(RunState(run, "not started", "not started"))
    return out


def labels(states) -> list[str]:
    return [r.label for r in states]


def test_state_bytes_from_the_parameter_count():
    cfg = preset("paper")
    vit_lstm = next(r for r in runs(cfg) if r.dir_name == "vit_lstm-state")
    # last.* squeezed: 0.85 of 12 bytes a parameter (fp32 moments), 0.78 of 8 (bf16); no best.* (select: last)
    assert state_bytes(cfg, vit_lstm, "fp32") == 36_349_362 + 196_608 == 36_545_970
    assert state_bytes(cfg, vit_lstm, "bf16") == 22_237_257 + 196_608 == 22_433_865
    # the vitfly arm flies the best epoch: best.* beside it, fp16 from a slot, fp32 for a run of train.cpu_models
    vitfly = preset("paper_vitfly")
    vit_lstm, unet_lstm = (next(r for r in runs(vitfly) if r.dir_name == f"{m}-state")
                           for m in ("vit_lstm", "unet_lstm"))
    assert state_bytes(vitfly, vit_lstm, "fp32") == 36_349_362 + 2 * 3_563_663 + 196_608 == 43_673_296
    assert state_bytes(vitfly, unet_lstm, "fp32") == 30_149_384 + 4 * 2_955_822 + 196_608 == 42_169_280


def test_paper_first_slot_starts_the_lead_and_leaves_the_cpu_models_to_the_cpu():
    cfg = preset("paper")
    slot = next_slot(cfg, rows(cfg, done={"convnet-state", "convnet-nostate"}), ROOM)
    assert labels(slot.start) == ["vit_lstm-state"] and slot.carry == []
    assert slot.back_bytes == 22_433_865  # carried back next time with bf16 moments
    # train.cpu_models in slot order (UNet+LSTM before LSTMnet), the draws last
    assert labels(slot.on_cpu) == ["unet_lstm-state", "lstmnet-state", "unet_lstm-nostate", "lstmnet-nostate",
                                   "unet_lstm-state-s1", "lstmnet-state-s1", "convnet-state-s1", "convnet-state-s2",
                                   "lstmnet-nostate-s1", "convnet-nostate-s1", "convnet-nostate-s2"]
    assert "would not fit the next carry" in slot.wait["vit-state"]  # 22.43e6 + 19.55e6 > 33.55e6
    assert list(slot.wait) == ["vit-state", "vit_lstm-nostate", "vit-nostate"]


@pytest.mark.parametrize("room, moments", [(64 * 2**20, "fp32"), (ROOM, "bf16"), (20 * 2**20, None)])
def test_a_carried_state_keeps_fp32_moments_where_they_fit(room, moments):
    """ViT+LSTM: 36.55e6 bytes with fp32 moments, 22.43e6 with bf16, against 67.1e6, 33.6e6 and 21.0e6 of room."""
    cfg = preset("paper")
    marker = {"epochs": 4, "max_epochs": 100, "epoch_s": 64.0}
    slot = next_slot(cfg, rows(cfg, unfinished={"vit_lstm-state": (50_135_040, marker)}), room)
    assert slot.moments.get("vit_lstm-state") == moments
    assert slot.no_room == ([] if moments else ["vit_lstm-state"])
    assert next_slot(cfg, rows(cfg, unfinished={"vit_lstm-state": (0, marker)}), 64 * 2**20,
                     moments="bf16").sizes == {"vit_lstm-state": 22_433_865}


@pytest.mark.parametrize("carried_moments, size", [(None, 36_545_970), ("bf16", 22_433_865)])
def test_travelling_light_a_slot_carries_one_large_run_and_starts_two_more(carried_moments, size):
    """60 MiB of room (62,914,560 bytes: the working tree travelling light, scripts/gpu_travel.py): ViT+LSTM, 7 of
    100 epochs at 40.5 s, travels with fp32 moments (36.55e6), or with bf16 ones (22.43e6) when it was restored
    from a carry in bf16 (fp32 would carry bf16's values no better); it will not finish, so it comes back with
    bf16 moments (22.43e6), and ViT's 19.55e6 fits beside it, ViT+LSTM without the state no more (64.42e6), ViT
    without it again (61,530,043; UNet+LSTM trains on the CPU, train.cpu_models). Unsqueezed, only ViT fitted
    (28.71e6 + 25.01e6 + 25.01e6 = 78.73e6)."""
    cfg = preset("paper")
    marker = {"epochs": 7, "max_epochs": 100, "epoch_s": 40.5, "first_epoch_s": 68.2,
              **({"carried_moments": carried_moments} if carried_moments else {})}
    slot = next_slot(cfg, rows(cfg, unfinished={"vit_lstm-state": (28_583_064, marker)}), 60 * 2**20)
    assert labels(slot.carry) == ["vit_lstm-state"] and slot.sizes == {"vit_lstm-state": size}
    assert labels(slot.start) == ["vit-state", "vit-nostate"]
    assert slot.back_bytes == 22_433_865 + 19_548_089 + 19_548_089 == 61_530_043
    assert "would not fit the next carry" in slot.wait["vit_lstm-nostate"]


@pytest.mark.parametrize("room, moments", [(50_000_000, ("bf16", "bf16")), (60 * 2**20, ("fp32", "bf16")),
                                           (70_000_000, ("fp32", "fp32"))])
def test_two_unfinished_runs_travel_together_before_either_travels_exactly(room, moments):
    """ViT+LSTM and ViT both unfinished: 22,433,865 + 19,548,089 = 41,981,954 bytes with bf16 moments fit
    50,000,000; ViT+LSTM's fp32 moments (36,545,970) would leave ViT out (56,094,059), so both go in bf16. In 60 MiB
    (62,914,560) ViT+LSTM's fp32 moments fit beside ViT's bf16 ones, ViT's fp32 ones (31,828,837) no more
    (68,374,807), which 70,000,000 holds."""
    cfg = preset("paper")
    marker = {"epochs": 20, "max_epochs": 100, "epoch_s": 40.0, "first_epoch_s": 70.0}
    slot = next_slot(cfg, rows(cfg, unfinished={"vit_lstm-state": (0, marker), "vit-state": (0, marker)}), room)
    assert labels(slot.carry) == ["vit_lstm-state", "vit-state"] and slot.no_room == []
    assert (slot.moments["vit_lstm-state"], slot.moments["vit-state"]) == moments
    assert sum(slot.sizes.values()) == {("bf16", "bf16"): 41_981_954, ("fp32", "bf16"): 56_094_059,
                                        ("fp32", "fp32"): 68_374_807}[moments]


@pytest.mark.parametrize("epoch_s, starts", [(10.0, []), (7.5, ["vit-state"])])
def test_a_carried_run_frees_the_next_carry_only_when_it_will_finish(epoch_s, starts):
    """60 epochs left: 600 s or 450 s, against 560 - 40 - 60 = 460 s of training in a slot; ViT's 19.55e6 bytes
    fit beside nothing, not beside ViT+LSTM's 22.43e6."""
    cfg = preset("paper")
    marker = {"epochs": 40, "max_epochs": 100, "epoch_s": epoch_s}
    slot = next_slot(cfg, rows(cfg, unfinished={"vit_lstm-state": (50_000_000, marker)}), ROOM)
    assert labels(slot.carry) == ["vit_lstm-state"] and labels(slot.start) == starts


@pytest.mark.parametrize("first_epoch_s, finishes", [(20.0, False), (10.0, True)])
def test_a_run_finishes_when_its_first_epoch_and_the_steady_ones_fit(first_epoch_s, finishes):
    """60 epochs left at 7.5 s after a first one of 20 s (compilation): 20 + 59 x 7.5 = 462.5 s > 460 s of
    training in a slot; after a first of 10 s, 452.5 s fits."""
    from scripts.gpu_plan import finishes as fits

    cfg = preset("paper")
    marker = {"epochs": 40, "max_epochs": 100, "epoch_s": 7.5, "first_epoch_s": first_epoch_s}
    (row,) = [r for r in rows(cfg, unfinished={"vit_lstm-state": (0, marker)}) if r.state == "unfinished"]
    assert fits(row, 560.0 - 40.0 - 60.0) is finishes


def test_carry_in_slot_order_within_the_room():
    cfg = preset("paper")
    big = {"epochs": 1, "max_epochs": 100, "epoch_s": 60.0}
    slot = next_slot(cfg, rows(cfg, unfinished={"lstmnet-state": (41_000_000, big), "vit-state": (43_000_000, big)}),
                     ROOM)
    assert labels(slot.carry) == ["vit-state"]  # ViT before LSTMnet (train.slot_order): 19.55e6 + 18.60e6 > 33.55e6
    # (a run of cpu_models left unfinished by a GPU slot goes on there)
    assert slot.no_room == ["lstmnet-state"] and slot.start == []


def test_a_follow_on_starts_the_next_runs_only_where_the_first_calls_could_all_finish():
    """paper_vitfly (the vitfly arm flies its best epoch, so best.* adds 2 bytes a parameter): its first slot starts
    ViT+LSTM and ViT (29,561,191 + 25,750,487 bytes home of 62,914,560; LSTMnet's 24,504,088 no more). Were LSTMnet
    trained on the card (the preset trains it on a CPU, train.cpu_models, as UNet+LSTM), then should both finish in
    the first call, the follow-on starts LSTMnet (train.slot_order), ResNet-18 (93.3e6, cannot travel) not beside
    it; as the preset is, nothing is left for a follow-on. The paper arm's slot carries ViT+LSTM with 93 epochs
    left at 40.5 s: it cannot finish, so there is no such follow-on."""
    cfg = preset("paper_vitfly")
    slot = next_slot(cfg, rows(cfg), 60 * 2**20)
    assert labels(slot.start) == ["vit_lstm-state", "vit-state"] and slot.back_bytes == 29_561_191 + 25_750_487
    assert slot_after(cfg, rows(cfg), slot, 60 * 2**20) is None
    on_card = replace(cfg, train=replace(cfg.train, cpu_models=["convnet", "unet_lstm"], draws={}))
    after = slot_after(on_card, rows(on_card), next_slot(on_card, rows(on_card), 60 * 2**20), 60 * 2**20)
    assert labels(after.start) == ["lstmnet-state"] and after.back_bytes == 24_504_088
    assert "cannot travel" in after.wait["resnet18-state"]
    paper = preset("paper")
    marker = {"epochs": 7, "max_epochs": 100, "epoch_s": 40.5, "first_epoch_s": 68.2}
    states = rows(paper, unfinished={"vit_lstm-state": (0, marker)})
    assert slot_after(paper, states, next_slot(paper, states, 60 * 2**20), 60 * 2**20) is None
    # 5 epochs left: 68.2 + 4 x 40.5 s fit a call's 460 s of training, so ViT+LSTM frees the next carry, and ViT,
    # ViT+LSTM and ViT without the state start beside it (19,548,089 + 22,433,865 + 19,548,089 bytes: the no-state
    # networks have as many parameters); that is every run left for the card (the others are train.cpu_models),
    # so no follow-on starts more
    marker.update(epochs=95)
    slot = next_slot(paper, states, 60 * 2**20)
    assert labels(slot.start) == ["vit-state", "vit_lstm-nostate", "vit-nostate"] and slot.back_bytes == 61_530_043
    assert slot_after(paper, states, slot, 60 * 2**20) is None


def test_resnet18_trains_alone_and_must_finish():
    cfg = preset("paper_vitfly")
    others = {"convnet-state", "lstmnet-state", "unet_lstm-state", "vit_lstm-state"}
    slot = next_slot(cfg, rows(cfg, done=others), ROOM)
    assert labels(slot.start) == ["vit-state"] and "cannot travel" in slot.wait["resnet18-state"]  # 93.3e6 bytes
    slot = next_slot(cfg, rows(cfg, done=others | {"vit-state"}), ROOM)
    assert labels(slot.start) == ["resnet18-state"] and "must finish inside this command" in slot.alone


def test_slot_plan_names_models_the_study_trains():
    with pytest.raises(VitflyError, match="train.cpu_models has 'convnet', which the study does not train; its "
                                          "models are vit, lstmnet"):
        preset("paper", models=["vit", "lstmnet"], nostate_models=["lstmnet"], cpu_models=["convnet"])
    with pytest.raises(VitflyError, match="train.slot_order must be a list of distinct model names"):
        preset("paper", models=["vit"], nostate_models=[], slot_order=["vit", "vit"])


def test_what_a_call_sends_beside_its_carry(tmp_path):
    """Tracked files, untracked ones git does not ignore and .whl/ (ignored, but always carried): 1000, 300 and 50
    bytes and the .gitignore (13); an ignored file (a run folder) and a deleted tracked file count nothing."""
    import subprocess

    from scripts.gpu_slots import travelling_bytes

    plain, repo = tmp_path / "plain", tmp_path / "repo"
    plain.mkdir()
    repo.mkdir()

    def git(*args):
        subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True)

    git("init", "-q")
    (repo / ".gitignore").write_text("runs/\n/.whl/\n")  # 13 bytes, untracked, not ignored
    (repo / "tracked.bin").write_bytes(b"x" * 1000)
    (repo / "gone.bin").write_bytes(b"x" * 7)
    git("add", "tracked.bin", "gone.bin")
    (repo / "gone.bin").unlink()
    (repo / "new.txt").write_bytes(b"y" * 300)
    (repo / "runs").mkdir()
    (repo / "runs" / "state.ckpt").write_bytes(b"z" * 5000)
    (repo / ".whl").mkdir()
    (repo / ".whl" / "a.whl").write_bytes(b"w" * 50)
    assert travelling_bytes(repo) == 1000 + 300 + 13 + 50
    for preset, size in (("paper", 700), ("paper_vitfly", 90)):  # two presets' carries, untracked, not ignored
        (repo / "carry" / preset / "vit-state").mkdir(parents=True)
        (repo / "carry" / preset / "vit-state" / "last.json").write_bytes(b"c" * size)
    assert travelling_bytes(repo) == 1000 + 300 + 13 + 50 + 700 + 90
    assert travelling_bytes(repo, leave_out=repo / "carry" / "paper") == 1000 + 300 + 13 + 50 + 90
    assert travelling_bytes(repo, leave_out=[repo / "carry" / "paper", repo / "carry" / "paper_vitfly"]) == 1363
    with pytest.raises(SystemExit, match="not a git checkout"):
        travelling_bytes(plain)


def test_a_plan_keeps_room_for_the_wheels_before_they_are_fetched(tmp_path):
    """A new checkout has no .whl/ yet, but every call will carry it: the plan keeps WHEELS_RESERVE for it (more
    than the 1.2 MiB the four wheels took on 2026-12-05); once fetched, travelling_bytes counts them instead."""
    from scripts.gpu_slots import WHEELS_RESERVE, wheels_reserve

    assert wheels_reserve(tmp_path) == WHEELS_RESERVE >= 1.2 * 2**20
    (tmp_path / ".whl").mkdir()
    assert wheels_reserve(tmp_path) == 0


def test_a_presets_slot_leaves_the_other_presets_carries_here(tmp_path):
    """carry/paper_vitfly's slot sends nothing of carry/paper (and the other way round): status plans without it
    and prints it in the `travel light --leave` line."""
    from scripts.gpu_carry import ROOT, other_carries

    for preset in ("paper", "paper_vitfly", "tiny"):
        (tmp_path / "carry" / preset).mkdir(parents=True)
    (tmp_path / "carry" / "notes.txt").write_text("not a preset")
    assert other_carries(tmp_path / "carry" / "paper") == [tmp_path / "carry" / "paper_vitfly",
                                                            tmp_path / "carry" / "tiny"]
    assert other_carries(tmp_path / "nowhere" / "paper") == []
    assert other_carries(ROOT / "paper") == []  # --carry-dir . would put the presets' carries in the repository's root
