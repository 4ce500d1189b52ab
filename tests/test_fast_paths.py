"""The training speed paths: device-resident dataset, compiled encoders, one-threaded LSTM, fused Adam, bf16.

Each fast path is checked against the plain path it replaces (same batches, same outputs, same update),
not against numbers of its own.
"""

from __future__ import annotations

import warnings

import lightning as L
import pytest
import torch
from test_datamodule import write_dataset

from vitfly.datamodules.datamodule import TrajectoryDataModule
from vitfly.datamodules.dataset import (
    HOST_LENGTHS,
    TrajectoryDataset,
    collate_trajectories,
    depth_to_unit_float,
    pad_to_bucket,
)
from vitfly.datamodules.resident import ResidentTrajectories, collate_windows, resident_bytes
from vitfly.errors import VitflyError
from vitfly.zoo import compile_encoder, create_model
from vitfly.zoo import compiled as compiled_module
from vitfly.zoo.policy import create_policy

LENGTHS = [10, 23, 17, 6, 31]


@pytest.fixture(scope="module")
def data_path(tmp_path_factory):
    return write_dataset(tmp_path_factory.mktemp("data") / "d.h5", LENGTHS)


def quiet_trainer(root, **kwargs) -> L.Trainer:
    return L.Trainer(
        default_root_dir=root,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        accelerator="cpu",
        **kwargs,
    )


# -- resident dataset ---------------------------------------------------------------------------


def test_resident_gather_equals_the_streamed_collate(data_path):
    store = ResidentTrajectories(data_path, "cpu")
    # 5 trajectories of LENGTHS steps plus the one zero padding row
    assert store.depth.shape == (sum(LENGTHS) + 1, 60, 90) and store.nbytes == resident_bytes(sum(LENGTHS)) + 8 * 5
    ds = TrajectoryDataset(data_path, max_length=8)  # windows: several per trajectory, starts != 0
    for items in ([0, 5, 2], [len(ds) - 1], [3, 4, 1, 7, 9]):
        expected = collate_trajectories([ds[i] for i in items], depth_dtype=torch.uint8)
        index = collate_windows([ds.windows[i] for i in items])
        got = store.gather(index["traj_index"], index["start"], index["length"])
        assert got.keys() == expected.keys()
        for key in expected:
            assert got[key].dtype == expected[key].dtype, key
            torch.testing.assert_close(got[key], expected[key], rtol=0, atol=0, msg=key)


def test_resident_loader_gives_the_streamed_batches(data_path):
    def batches(resident):
        dm = TrajectoryDataModule(data_path, batch_size=2, val_fraction=0.4, resident=resident, max_length=12)
        dm.setup("fit")
        out = {}
        for name, loader in (("train", dm.train_dataloader()), ("val", dm.val_dataloader())):
            out[name] = [dm.on_after_batch_transfer(dm.on_before_batch_transfer(b, 0), 0) for b in loader]
        return out

    streamed, resident = batches(False), batches(True)
    for name in ("train", "val"):
        assert len(resident[name]) == len(streamed[name]) > 0
        for a, b in zip(resident[name], streamed[name], strict=True):
            assert a["depth"].dtype == torch.float32
            # the rows' lengths as the host had them before the trip: the streamed batch's mask, counted
            assert a.pop(HOST_LENGTHS).tolist() == b["mask"].sum(dim=1).tolist()
            assert a.keys() == b.keys()
            for key in a:
                torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, msg=key)


def test_resident_auto_stays_off_the_cpu_and_bad_values_fail(data_path):
    dm = TrajectoryDataModule(data_path)
    assert dm.resident == "auto" and not dm.use_resident(torch.device("cpu"))
    assert TrajectoryDataModule(data_path, resident=True).use_resident(torch.device("cpu"))
    with pytest.raises(VitflyError, match="resident: expected true, false or auto"):
        TrajectoryDataModule(data_path, resident="yes")


def test_fit_on_a_resident_dataset_takes_the_streamed_number_of_steps(data_path, tmp_path):
    steps = []
    for resident in (False, True):
        torch.manual_seed(0)
        module = create_policy("convnet", tbptt_steps=8, warmup_epochs=0)
        dm = TrajectoryDataModule(data_path, batch_size=2, val_fraction=0.2, resident=resident)
        trainer = quiet_trainer(tmp_path / str(resident), max_epochs=2)
        trainer.fit(module, datamodule=dm)
        steps.append(trainer.global_step)
        assert torch.isfinite(trainer.callback_metrics["val/loss"])
    assert steps[0] == steps[1] > 0


# -- truncated BPTT bookkeeping ------------------------------------------------------------------


def test_chunks_carry_valid_counts_worked_out_from_the_lengths(data_path):
    ds = TrajectoryDataset(data_path)
    batch = depth_to_unit_float(collate_trajectories([ds[i] for i in (0, 1, 3)]))  # lengths 10, 23, 6
    module = create_policy("convnet", tbptt_steps=8)
    chunks = list(module.tbptt_chunks(batch))
    # by hand: steps 0-7 valid for 8+8+6, 8-15 for 2+8+0, 16-22 for 0+7+0
    assert [c["n_valid"] for c in chunks] == [22, 10, 7]
    assert [c["all_valid"] for c in chunks] == [False, False, False]
    assert [c["mask"].shape[1] for c in chunks] == [8, 8, 7]
    (whole,) = create_policy("convnet", tbptt_steps=None).tbptt_chunks(
        depth_to_unit_float(collate_trajectories([ds[1]]))
    )
    assert whole["n_valid"] == 23 and whole["all_valid"]


@pytest.mark.parametrize("static_shapes", [False, True])
def test_chunks_from_the_hosts_lengths_never_wait_for_the_device(data_path, static_shapes):
    """A resident batch carries its rows' lengths on the host (``lengths_host``), padded to a bucket of 32 steps
    and 4 rows: its chunks are the ones its mask gives, and come without a copy of the mask to the host (here a
    mask on the meta device, which cannot be copied: a host copy would raise)."""
    dm = TrajectoryDataModule(data_path, batch_size=4, val_fraction=0.0, resident=True, time_bucket_steps=32)
    dm.setup("fit")
    index = collate_windows([(0, 0, 10), (1, 0, 23), (3, 0, 6)])  # lengths 10, 23, 6: a short last batch
    # the trip to a device leaves the lengths on the host (here the meta device: no data, only shapes)
    moved = dm.transfer_batch_to_device(dm.on_before_batch_transfer(dict(index), 0), torch.device("meta"), 0)
    assert moved["length"].is_meta and moved["traj_index"].is_meta and moved[HOST_LENGTHS].device.type == "cpu"
    batch = pad_to_bucket(dm.on_after_batch_transfer(dm.on_before_batch_transfer(index, 0), 0), 32, 4)
    assert batch[HOST_LENGTHS].tolist() == [10, 23, 6, 0] and batch["mask"].shape == (4, 32)
    module = create_policy("convnet", tbptt_steps=8, static_shapes=static_shapes)
    expected = [(c["n_valid"], c["all_valid"], c["mask"].shape) for c in module.tbptt_chunks(
        {k: v for k, v in batch.items() if k != HOST_LENGTHS})]
    # by hand: steps 0-7 valid for 8+8+6, 8-15 for 2+8, 16-22 for 7 (16-23 with static shapes: whole chunks)
    assert [(n, tuple(shape)) for n, _, shape in expected] == [(22, (4, 8)), (10, (4, 8)),
                                                               (7, (4, 8 if static_shapes else 7))]
    on_meta = {**batch, **{k: batch[k].to("meta") for k in ("depth", "desired_speed", "quat", "velocity_cmd",
                                                              "mask")}}
    with pytest.raises(NotImplementedError):
        on_meta["mask"].cpu()
    got = [(c["n_valid"], c["all_valid"], c["mask"].shape) for c in module.tbptt_chunks(on_meta)]
    assert got == expected


# -- one-threaded LSTM, fused Adam ---------------------------------------------------------------


def test_lstm_training_restores_the_thread_count_and_matches_nn_lstm():
    torch.manual_seed(0)
    net = create_model("lstmnet")
    net.eval()  # with autograd on: the training LSTM path, without dropout and spectral-norm updates
    depth = torch.rand(2, 5, 1, 60, 90)
    speed, quat = torch.full((2, 5, 1), 4.0), torch.nn.functional.normalize(torch.randn(2, 5, 4), dim=-1)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        out, _ = net(depth, speed, quat)
        assert torch.get_num_threads() == 2
        out.square().sum().backward()
        assert torch.get_num_threads() == 2  # set to 1 for the LSTM's backward, restored after it
        grads = [p.grad.clone() for p in net.lstm.parameters()]
        net.zero_grad()
        features = net.encode(depth.reshape(10, 1, 60, 90)).reshape(2, 5, -1)
        x = torch.cat((features, torch.cat((speed * 0.1, quat), -1)), -1)
        ref, _ = net.lstm(x)
        ref_out = net.fc3(torch.nn.functional.leaky_relu(net.fc2(torch.nn.functional.leaky_relu(net.fc1(ref)))))
        ref_out.square().sum().backward()
        for g, p in zip(grads, net.lstm.parameters(), strict=True):
            # one thread and two sum in different orders: equal to float32 rounding
            torch.testing.assert_close(g, p.grad, rtol=1e-5, atol=1e-5 * float(p.grad.abs().max()))
    finally:
        torch.set_num_threads(threads)


def test_adam_is_fused_on_the_cpu():
    module = create_policy("convnet")
    opt = module.configure_optimizers()
    assert opt.param_groups[0]["fused"] is True


def two_adam_steps(module, grads, reload: bool) -> torch.Tensor:
    """The network's weights (flat, contiguous) after two steps of its own optimiser on ``grads``; with
    ``reload`` the optimiser is rebuilt between them from its state dict with contiguous moments, as a resume
    from vitfly's checkpoint files (safetensors holds contiguous tensors) gives them."""
    params = list(module.net.parameters())
    opt = module.configure_optimizers()
    for step in range(2):
        for p, g in zip(params, grads[step], strict=True):
            p.grad = g.clone().to(memory_format=torch.channels_last) if p.dim() == 4 and not p.is_contiguous() \
                else g.clone()
        opt.step()
        if reload and step == 0:
            state = opt.state_dict()
            for moments in state["state"].values():
                for key, value in moments.items():
                    moments[key] = value.contiguous()
            opt = module.configure_optimizers()
            opt.load_state_dict(state)
    return torch.cat([p.detach().contiguous().flatten() for p in params])


def test_adam_in_another_memory_layout_updates_as_the_contiguous_network():
    """A network in channels-last layout takes the unfused Adam (torch's fused CPU kernel, given such a parameter
    with contiguous moments, updates it wrongly), so two steps across a resume give the contiguous network's
    weights."""
    torch.manual_seed(0)
    reference = create_policy("convnet", lr=1e-2, warmup_epochs=0)
    other = create_policy("convnet", lr=1e-2, warmup_epochs=0)
    other.load_state_dict(reference.state_dict())
    other.net.to(memory_format=torch.channels_last)
    assert any(not p.is_contiguous() for p in other.net.parameters())
    grads = [[torch.randn_like(p) for p in reference.net.parameters()] for _ in range(2)]
    want = two_adam_steps(reference, grads, reload=True)
    torch.testing.assert_close(two_adam_steps(other, grads, reload=True), want, rtol=0, atol=1e-6)
    assert other.configure_optimizers().param_groups[0]["fused"] is None


def test_a_resumed_network_in_another_layout_drops_the_fused_flag(data_path, tmp_path):
    """The checkpoint's optimiser groups bring back ``fused: True`` from a contiguous run; resumed in channels-last
    layout, the run trains with the unfused kernel."""
    torch.manual_seed(0)
    module = create_policy("convnet", warmup_epochs=0)
    dm = TrajectoryDataModule(data_path, batch_size=2, val_fraction=0.2, resident=False)
    trainer = quiet_trainer(tmp_path, max_epochs=1)
    trainer.fit(module, datamodule=dm)
    trainer.save_checkpoint(tmp_path / "one.ckpt")
    assert trainer.optimizers[0].param_groups[0]["fused"] is True
    seen = []

    class Flag(L.Callback):
        def on_train_batch_start(self, trainer, *args):
            seen.append(trainer.optimizers[0].param_groups[0]["fused"])

    resumed = create_policy("convnet", warmup_epochs=0)
    resumed.net.to(memory_format=torch.channels_last)
    trainer = quiet_trainer(tmp_path, max_epochs=2, callbacks=[Flag()])
    trainer.fit(resumed, datamodule=dm, ckpt_path=tmp_path / "one.ckpt")
    assert seen and set(seen) == {None}


def test_channels_last_on_the_cpu_trains_in_that_layout_unfused(data_path, tmp_path):
    """``channels_last: cpu`` on a CPU trainer: the convolutions' weights train channels-last, with the unfused
    Adam, and the checkpoint loads into a plain network; ``false`` leaves them contiguous and fused."""
    from vitfly.zoo import load_network

    for setting, layout, fused in (("cpu", torch.channels_last, None), (False, torch.contiguous_format, True)):
        torch.manual_seed(0)
        module = create_policy("convnet", warmup_epochs=0, channels_last=setting)
        dm = TrajectoryDataModule(data_path, batch_size=2, val_fraction=0.2, resident=False)
        trainer = quiet_trainer(tmp_path / str(setting), max_epochs=1)
        trainer.fit(module, datamodule=dm)
        convs = [p for p in module.net.parameters() if p.dim() == 4]
        assert convs and all(p.is_contiguous(memory_format=layout) for p in convs)
        assert trainer.optimizers[0].param_groups[0]["fused"] is fused
        trainer.save_checkpoint(tmp_path / f"{setting}.ckpt")
        loaded = load_network(tmp_path / f"{setting}.ckpt")
        for a, b in zip(module.net.state_dict().values(), loaded.state_dict().values(), strict=True):
            assert torch.equal(a, b)


def test_a_bad_channels_last_is_one_error():
    with pytest.raises(VitflyError, match="model.channels_last: expected false, true or cpu, got 'gpu'"):
        create_policy("convnet", channels_last="gpu")


# -- torch.compile -------------------------------------------------------------------------------


def test_compile_falls_back_to_eager_with_one_warning(monkeypatch):
    monkeypatch.setattr(compiled_module, "compiler_missing", lambda device_type="cpu": "no C++ compiler found")
    monkeypatch.setattr(compiled_module, "_WARNED", set())
    torch.manual_seed(0)
    net = create_model("convnet").eval()
    frames = torch.rand(3, 1, 60, 90)
    with torch.no_grad():
        expected = net.encode(frames)
    compile_encoder(net)
    assert compile_encoder(net) is net  # idempotent
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with torch.no_grad():
            first, second = net.encode(frames), net.encode(frames)
    messages = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    assert messages == ["torch.compile unavailable for ConvNet.encode: no C++ compiler found; running it eagerly"]
    torch.testing.assert_close(first, expected, rtol=0, atol=0)
    torch.testing.assert_close(second, expected, rtol=0, atol=0)
    assert set(net.state_dict()) == set(create_model("convnet").state_dict())


@pytest.mark.slow
@pytest.mark.parametrize("name", ["convnet", "vit_lstm"])
def test_compiled_encoder_matches_eager(name):
    torch.manual_seed(0)
    net = create_model(name).eval()
    frames = torch.rand(6, 1, 60, 90)
    with torch.no_grad():
        expected = net.encode(frames)
        compile_encoder(net)
        got, fewer = net.encode(frames), net.encode(frames[:4])  # a second frame count: no error, same values
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(fewer, expected[:4], rtol=1e-5, atol=1e-5)


# -- CPU thread count ----------------------------------------------------------------------------


def test_thread_tuner_keeps_the_measured_faster_count_and_measures_again(monkeypatch):
    from vitfly.zoo import thread_tuner

    clock = {"now": 0.0}
    monkeypatch.setattr(thread_tuner.time, "perf_counter", lambda: clock["now"])
    start = torch.get_num_threads()
    seconds_per_frame = {2: 0.010, 1: 0.002}  # an oversubscribed machine: one thread 5x faster

    def step(tuner, frames=100):
        tuner.before_step()
        clock["now"] += seconds_per_frame[torch.get_num_threads()] * frames
        tuner.after_step(frames)
        return torch.get_num_threads()

    try:
        tuner = thread_tuner.ThreadTuner(max_threads=2, probe_steps=3, probe_every=5)
        # probing alternates 2, 1, 2, 1, 2, 1; then 1 thread for 5 steps; then it measures again
        assert [step(tuner) for _ in range(11)] == [2, 1, 2, 1, 2, 1, 1, 1, 1, 1, 1]
        seconds_per_frame.update({2: 0.001})  # the other load went away: two threads now win
        assert [step(tuner, frames=50) for _ in range(6 + 3)] == [2, 1, 2, 1, 2, 1, 2, 2, 2]
        tuner.restore()
        assert torch.get_num_threads() == 2
        assert not thread_tuner.ThreadTuner(max_threads=1).active
    finally:
        torch.set_num_threads(start)


def test_cpu_threads_is_checked_and_a_number_is_applied(data_path, tmp_path):
    with pytest.raises(VitflyError, match="model.cpu_threads: expected auto"):
        create_policy("convnet", cpu_threads=0)
    start = torch.get_num_threads()
    try:
        module = create_policy("convnet", cpu_threads=1, tbptt_steps=16)
        trainer = quiet_trainer(tmp_path, max_epochs=1, limit_val_batches=0)
        trainer.fit(module, datamodule=TrajectoryDataModule(data_path, batch_size=2, val_fraction=0.0))
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(start)
