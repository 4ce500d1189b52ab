"""bf16 autocast only where the CPU has bf16 kernels: elsewhere a CPU run trains in fp32 and says so in one line."""

from __future__ import annotations

import platform
from pathlib import Path

import lightning as L
import pytest
import yaml
from test_datamodule import write_dataset

from vitfly.cli import main
from vitfly.training import precision
from vitfly.training.fit import train_policy

REPO = Path(__file__).resolve().parents[1]


def cpu_flags() -> set[str]:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("flags"):
            return set(line.partition(":")[2].split())
    return set()


@pytest.mark.skipif(platform.machine() != "x86_64" or not Path("/proc/cpuinfo").exists(), reason="x86 Linux")
def test_bf16_kernels_follow_the_cpu_flags():
    """oneDNN's bf16 kernels need AVX512 at least: none without any avx512 flag, always with AVX512-BF16 or AMX."""
    flags = cpu_flags()
    if any(f.startswith("avx512") for f in flags) and not {"avx512_bf16", "amx_bf16"} & flags:
        pytest.skip("AVX512 without AVX512-BF16 or AMX: oneDNN's choice there is its own")
    if not any(f.startswith("avx512") for f in flags):
        assert precision.cpu_has_native_bf16() is False
    if {"avx512_bf16", "amx_bf16"} & flags:
        assert precision.cpu_has_native_bf16() is True


@pytest.fixture
def no_bf16_kernels(monkeypatch):
    """This CPU as one without bf16 kernels (the AVX2-only machines), whatever it is."""
    monkeypatch.delenv(precision.KEEP_ENV, raising=False)
    monkeypatch.setattr(precision, "cpu_has_native_bf16", lambda: False)


def test_bf16_autocast_becomes_fp32_on_a_cpu_without_bf16_kernels(no_bf16_kernels, monkeypatch, capsys):
    asked, callbacks = precision.usable_precision("bf16-mixed", "cpu", "fit vit")
    assert asked == "32-true" and [type(c).__name__ for c in callbacks] == ["PrecisionNote"]
    assert precision.usable_precision("bf16", None)[0] == "32-true"  # Lightning's "auto" on a machine without GPU
    # what is not bf16 autocast on the CPU is left as asked, with nothing to say
    for asked, accelerator in (("32-true", "cpu"), ("bf16-true", "cpu"), ("16-mixed", "cpu"), ("bf16-mixed", "gpu"),
                               ("bf16-mixed", "cuda"), (None, "cpu")):
        assert precision.usable_precision(asked, accelerator) == (asked, [])
    monkeypatch.setenv(precision.KEEP_ENV, "1")
    assert precision.usable_precision("bf16", "cpu") == ("bf16", [])
    assert precision.trainer_precision({"max_time": "00:00:01:00"}) == ({"max_time": "00:00:01:00"}, [])
    assert capsys.readouterr().err == ""  # the note speaks when a Trainer sets up, not before


class RecordPrecision(L.Callback):
    def on_train_start(self, trainer, pl_module):
        self.precision = trainer.precision


def test_train_policy_and_vitfly_fit_run_fp32_there(no_bf16_kernels, tmp_path, capsys):
    data = write_dataset(tmp_path / "d.h5", [9, 7, 11, 8, 10])
    record = RecordPrecision()
    train_policy(data, "convnet", tmp_path / "run", max_epochs=1, batch_size=2, progress_bar=False,
                 data_kwargs={"num_workers": 0}, trainer_kwargs={"precision": "bf16-mixed", "accelerator": "cpu"},
                 callbacks=[record])
    assert record.precision == "32-true"
    (line,) = capsys.readouterr().err.splitlines()  # said once
    assert line.startswith("train convnet: this CPU has no bf16 kernels") and "VITFLY_CPU_BF16=1 keeps bf16" in line

    # vitfly fit with a shipped ViT config (bf16-mixed): the config it saves is the one that ran
    root = tmp_path / "fit"
    assert main(["fit", "--config", str(REPO / "configs/fit/vit.yaml"), "--data.data_path", data,
                 "--data.num_workers", "0", "--data.batch_size", "2", "--trainer.max_epochs", "1",
                 "--trainer.limit_train_batches", "1", "--trainer.limit_val_batches", "1",
                 "--trainer.default_root_dir", str(root), "--trainer.enable_progress_bar", "false"]) == 0
    err = capsys.readouterr().err
    assert "vitfly fit: this CPU has no bf16 kernels (they need AVX512 or AMX), so precision bf16-mixed would be " \
        "emulated" in err
    (saved,) = root.glob("version_*/config.yaml")
    assert yaml.safe_load(saved.read_text())["trainer"]["precision"] == "32-true"
