"""Original-project checkpoints: exact reproduction of the stored outputs, clear errors, conversion."""

from __future__ import annotations

import os
from pathlib import Path

import lightning as L
import pytest
import torch

from vitfly.cli import main
from vitfly.errors import VitflyError
from vitfly.zoo import create_model, load_legacy_checkpoint, load_network

torch.set_num_threads(1)

FIXTURES = Path(
    os.environ.get("VITFLY_LEGACY_FIXTURES", Path(__file__).resolve().parents[1] / ".." / "shared/fixtures/legacy")
)
ARCHS = ["convnet", "lstmnet", "unet_lstm", "vit", "vit_lstm"]

pytestmark = pytest.mark.skipif(
    not (FIXTURES / "convnet.pth").exists(),
    reason=f"original-checkpoint fixtures not found in {FIXTURES} (set VITFLY_LEGACY_FIXTURES)",
)


def _io(arch: str) -> dict[str, torch.Tensor]:
    return torch.load(FIXTURES / f"{arch}_io.pt", weights_only=True)


def _run(net, io, grad: bool):
    args = (io["depth"][None], io["desired_speed"][None], io["quat"][None])  # 12 frames = one sequence
    if grad:
        out, hidden = net(*args)
        return out.detach(), None if hidden is None else tuple(h.detach() for h in hidden)
    with torch.inference_mode():
        return net(*args)


def _check_reproduces(net, arch: str, grad: bool = False) -> None:
    io = _io(arch)
    out, hidden = _run(net, io, grad)
    torch.testing.assert_close(out[0], io["velocity"], atol=1e-5, rtol=0)
    if "h_n" in io:
        torch.testing.assert_close(hidden[0][:, 0], io["h_n"], atol=1e-5, rtol=0)
        torch.testing.assert_close(hidden[1][:, 0], io["c_n"], atol=1e-5, rtol=0)
    else:
        assert hidden is None


@pytest.mark.parametrize("grad", [False, True], ids=["inference", "autograd"])
@pytest.mark.parametrize("arch", ARCHS)
def test_original_checkpoints_reproduce_stored_outputs(arch, grad):
    net = load_legacy_checkpoint(arch, FIXTURES / f"{arch}.pth")
    assert not net.training
    _check_reproduces(net, arch, grad)


def test_recurrent_state_carried_frame_by_frame_matches_the_sequence_call():
    net = load_legacy_checkpoint("vit_lstm", FIXTURES / "vit_lstm.pth")
    io = _io("vit_lstm")
    hidden, outputs = None, []
    with torch.inference_mode():
        for t in range(io["depth"].shape[0]):  # as in flight: one frame per call
            out, hidden = net(io["depth"][None, t : t + 1], io["desired_speed"][None, t : t + 1], io["quat"][None, t : t + 1], hidden)  # noqa: E501
            outputs.append(out[0, 0])
    torch.testing.assert_close(torch.stack(outputs), io["velocity"], atol=1e-5, rtol=0)
    torch.testing.assert_close(hidden[1][:, 0], io["c_n"], atol=1e-5, rtol=0)


def test_another_architecture_is_named():
    with pytest.raises(VitflyError) as err:
        load_legacy_checkpoint("vit", FIXTURES / "vit_lstm.pth")
    message = str(err.value)
    assert "vit_lstm.pth: does not fit architecture 'vit'" in message
    assert "unexpected keys" in message and "lstm.weight_ih_l0" in message
    assert "looks like a 'vit_lstm' checkpoint" in message
    assert "\n" not in message


def test_missing_extra_and_misshapen_keys(tmp_path):
    state = torch.load(FIXTURES / "convnet.pth", weights_only=True)
    missing = dict(state)
    del missing["fc3.bias"]
    torch.save(missing, tmp_path / "missing.pth")
    with pytest.raises(VitflyError, match=r"missing.pth: does not fit architecture 'convnet': missing keys fc3.bias"):
        load_legacy_checkpoint("convnet", tmp_path / "missing.pth")
    extra = dict(state, **{"fc4.weight": torch.zeros(3, 3)})
    torch.save(extra, tmp_path / "extra.pth")
    with pytest.raises(VitflyError, match=r"unexpected keys fc4.weight"):
        load_legacy_checkpoint("convnet", tmp_path / "extra.pth")
    misshapen = dict(state, **{"fc3.weight": torch.zeros(3, 16)})
    torch.save(misshapen, tmp_path / "misshapen.pth")
    with pytest.raises(VitflyError, match=r"wrong shapes fc3.weight \(3, 16\) \(expected \(3, 32\)\)"):
        load_legacy_checkpoint("convnet", tmp_path / "misshapen.pth")


def test_truncated_and_foreign_files(tmp_path):
    data = (FIXTURES / "lstmnet.pth").read_bytes()
    (tmp_path / "cut.pth").write_bytes(data[: len(data) // 2])
    with pytest.raises(VitflyError, match=r"cut.pth: not a readable PyTorch checkpoint \(truncated"):
        load_legacy_checkpoint("lstmnet", tmp_path / "cut.pth")
    (tmp_path / "notes.pth").write_text("hello")
    with pytest.raises(VitflyError, match="notes.pth: not a readable PyTorch checkpoint"):
        load_legacy_checkpoint("lstmnet", tmp_path / "notes.pth")
    torch.save([torch.zeros(2)], tmp_path / "list.pth")
    with pytest.raises(VitflyError, match=r"list.pth: not a state dict \(expected a mapping .* got list\)"):
        load_legacy_checkpoint("lstmnet", tmp_path / "list.pth")
    with pytest.raises(VitflyError, match="unknown model 'transformer'"):
        load_legacy_checkpoint("transformer", FIXTURES / "vit.pth")


def test_load_network_recognises_an_original_state_dict():
    net = load_network(FIXTURES / "unet_lstm.pth")
    assert type(net).__name__ == "UNetLSTM"
    _check_reproduces(net, "unet_lstm")


class _MinimalPolicy(L.LightningModule):
    """The constructor shape of the training module (contract 2), to load converted files with Lightning."""

    def __init__(self, model: str, use_state: bool = True, model_kwargs: dict | None = None) -> None:
        super().__init__()
        self.save_hyperparameters()
        self.net = create_model(model, use_state=use_state, **(model_kwargs or {}))


@pytest.mark.parametrize("arch", ["lstmnet", "vit"])
def test_convert_checkpoint_command(tmp_path, capsys, arch):
    out = tmp_path / f"{arch}.ckpt"
    assert main(["convert-checkpoint", str(FIXTURES / f"{arch}.pth"), "--arch", arch, "--out", str(out)]) == 0
    assert f"wrote {out}: {arch}" in capsys.readouterr().out
    _check_reproduces(load_network(out), arch)  # loads by path alone
    module = _MinimalPolicy.load_from_checkpoint(out, map_location="cpu")
    assert module.hparams.model == arch
    _check_reproduces(module.net.eval(), arch)
    # refuses to overwrite, and a wrong --arch is one line naming the likely architecture
    assert main(["convert-checkpoint", str(FIXTURES / f"{arch}.pth"), "--arch", arch, "--out", str(out)]) == 2
    bad = tmp_path / "bad.ckpt"
    assert main(["convert-checkpoint", str(FIXTURES / "convnet.pth"), "--arch", arch, "--out", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "already exists" in err and "looks like a 'convnet' checkpoint" in err
    assert not bad.exists()


def test_convert_checkpoint_recognises_the_architecture(tmp_path):
    out = tmp_path / "auto.ckpt"
    assert main(["convert-checkpoint", str(FIXTURES / "vit_lstm.pth"), "--out", str(out)]) == 0
    assert torch.load(out, weights_only=True)["hyper_parameters"]["model"] == "vit_lstm"
