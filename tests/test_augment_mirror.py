"""Left-right mirror augmentation: the labels stay right, checked against the simulator itself.

The mirror of the world in the x-z plane is M = diag(1, -1, 1). Worked out by hand: a rotation R maps to
M R M, the rotation by the same angle about -M n, so the quaternion (w, x, y, z) becomes (w, -x, y, -z);
world-frame velocities become (x, -y, z); a body-frame point b = R^T (p - c) becomes M b, so the camera's
image is flipped left-right. Here the simulator's own camera and expert confirm it on a real scene.
"""

from __future__ import annotations

import lightning as L
import numpy as np
import pytest
import torch
from test_datamodule import write_dataset

from vitfly.datamodules.augment import mirror_coins, mirror_items, random_mirror
from vitfly.datamodules.datamodule import TrajectoryDataModule
from vitfly.datamodules.dataset import TrajectoryDataset, collate_trajectories
from vitfly.errors import VitflyError
from vitfly.sim.camera import DepthCamera
from vitfly.sim.expert import ExpertConfig, blocked_waypoints, expert_command, waypoint_grid
from vitfly.sim.quadrotor import quat_wxyz_to_matrix
from vitfly.sim.scenes import Scene, make_scene
from vitfly.zoo.policy import create_policy

M = np.diag([1.0, -1.0, 1.0])
torch.set_num_threads(1)


def random_quats(n: int, seed: int = 0) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def mirror_quat_np(q: np.ndarray) -> np.ndarray:
    batch = {"depth": torch.zeros(1, len(q), 1, 2, 2), "quat": torch.as_tensor(q, dtype=torch.float64)[None],
             "velocity_cmd": torch.zeros(1, len(q), 3, dtype=torch.float64)}
    return mirror_items(batch, torch.tensor([True]))["quat"][0].numpy()


def mirrored_scene(scene: Scene) -> Scene:
    spheres = scene.spheres.copy()
    spheres[:, 1] *= -1.0
    return Scene(scene.env, scene.preset, scene.seed, spheres, scene.cylinders, scene.boxes)


def test_mirrored_quaternion_is_the_reflected_rotation():
    q = random_quats(200)
    rot = quat_wxyz_to_matrix(q)
    rot_mirrored = quat_wxyz_to_matrix(mirror_quat_np(q))
    np.testing.assert_allclose(rot_mirrored, M @ rot @ M, atol=1e-12)
    # the same as writing it out: (w, -x, y, -z)
    np.testing.assert_array_equal(mirror_quat_np(q), q * np.array([1, -1, 1, -1]))


def test_camera_sees_the_mirrored_scene_as_the_flipped_image():
    scene = make_scene("spheres", "medium", seed=4)
    # an off-centre, tilted and yawed pose among the spheres
    position = np.array([17.0, 0.8, 3.1])
    (q,) = random_quats(1, seed=3) * 0.15 + np.array([1.0, 0, 0, 0])
    q /= np.linalg.norm(q)
    rot = quat_wxyz_to_matrix(q)[0]
    camera = DepthCamera()
    image = camera.render(scene, position, rot)
    assert (image < 1.0).mean() > 0.1  # spheres in view, not an empty image
    rot_m = quat_wxyz_to_matrix(mirror_quat_np(q[None]))[0]
    image_m = camera.render(mirrored_scene(scene), M @ position, rot_m)
    # the pixel columns are symmetric about the optical axis: the same image, flipped (to float rounding)
    np.testing.assert_allclose(image_m, image[:, ::-1], atol=1e-6)
    # and the augmentation does to the stored image what the mirrored world does to the rendered one
    depth = torch.from_numpy(image)[None, None, None]
    batch = {"depth": depth, "quat": torch.from_numpy(q)[None, None], "velocity_cmd": torch.zeros(1, 1, 3)}
    flipped = mirror_items(batch, torch.tensor([True]))["depth"][0, 0, 0].numpy()
    np.testing.assert_allclose(image_m, flipped, atol=1e-6)


def untied_avoidance_position(scene: Scene, cfg: ExpertConfig) -> np.ndarray:
    """A position along the scene where the expert swerves sideways and its choice has no tie."""
    _, manhattan = waypoint_grid(cfg)
    obstacles = scene.expert_obstacles()
    for x in np.arange(6.0, 50.0, 0.25):
        pos = np.array([x, 0.3, 3.5])
        free = ~blocked_waypoints(obstacles - np.concatenate([pos, [0.0]]), cfg)
        if free.all() or not free.any():
            continue
        best = manhattan[free].min()
        cmd = expert_command(pos, obstacles, 5.0, cfg)
        if (manhattan[free] == best).sum() == 1 and abs(cmd[1]) > 0.5:
            return pos
    raise AssertionError("no untied avoidance manoeuvre found in the scene")


def test_expert_command_in_the_mirrored_scene_is_the_mirrored_command():
    cfg = ExpertConfig()
    scene = make_scene("spheres", "medium", seed=4)
    pos = untied_avoidance_position(scene, cfg)
    cmd = expert_command(pos, scene.expert_obstacles(), 5.0, cfg)
    cmd_m = expert_command(M @ pos, mirrored_scene(scene).expert_obstacles(), 5.0, cfg)
    np.testing.assert_allclose(cmd_m, M @ cmd, atol=1e-12)
    batch = {"depth": torch.zeros(1, 1, 1, 2, 2), "quat": torch.tensor([[[1.0, 0, 0, 0]]]),
             "velocity_cmd": torch.tensor(cmd, dtype=torch.float64)[None, None]}
    np.testing.assert_allclose(mirror_items(batch, torch.tensor([True]))["velocity_cmd"][0, 0].numpy(), cmd_m)


def test_mirror_items_touches_only_the_chosen_items_and_not_the_input(tmp_path):
    path = write_dataset(tmp_path / "d.h5", [5, 8, 3])
    ds = TrajectoryDataset(path)
    batch = collate_trajectories([ds[i] for i in range(3)], depth_dtype=torch.uint8)
    before = {k: v.clone() for k, v in batch.items()}
    out = mirror_items(batch, torch.tensor([False, True, False]))
    for k in batch:
        assert torch.equal(batch[k], before[k])  # the input batch is left as it was
    for i in (0, 2):
        for k in ("depth", "quat", "velocity_cmd", "mask"):
            assert torch.equal(out[k][i], batch[k][i])
    assert torch.equal(out["depth"][1], batch["depth"][1].flip(-1))
    assert torch.equal(out["velocity_cmd"][1], batch["velocity_cmd"][1] * torch.tensor([1.0, -1.0, 1.0]))
    assert torch.equal(out["quat"][1], batch["quat"][1] * torch.tensor([1.0, -1.0, 1.0, -1.0]))
    assert torch.equal(out["mask"], batch["mask"])
    assert out["depth"].dtype == torch.uint8


def test_coins_follow_the_probability_and_not_the_batch_order():
    traj = torch.arange(400)
    start = torch.zeros(400, dtype=torch.long)
    coins = mirror_coins(traj, start, 0.5, seed=0, epoch=3)
    assert 160 < int(coins.sum()) < 240  # binomial(400, 0.5): within 4 standard deviations
    perm = torch.randperm(400, generator=torch.Generator().manual_seed(1))
    assert torch.equal(mirror_coins(traj[perm], start[perm], 0.5, seed=0, epoch=3), coins[perm])
    assert not torch.equal(mirror_coins(traj, start, 0.5, seed=0, epoch=4), coins)  # a new draw per epoch
    assert mirror_coins(traj, start, 1.0, 0, 0).all() and not mirror_coins(traj, start, 0.0, 0, 0).any()
    batch = {"depth": torch.ones(2, 1, 1, 2, 2), "quat": torch.ones(2, 1, 4), "velocity_cmd": torch.ones(2, 1, 3),
             "traj_index": torch.tensor([0, 1])}
    assert random_mirror(batch, 0.0, 0, 0) is batch


class RecordBatches(L.Callback):
    def __init__(self):
        self.train, self.val = [], []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.train.append({k: v.clone() for k, v in batch.items()})

    def on_validation_batch_start(self, trainer, pl_module, batch, batch_idx, dataloader_idx=0):
        self.val.append({k: v.clone() for k, v in batch.items()})


def record_batches(dm, root) -> RecordBatches:
    """One epoch of a ConvNet on ``dm``; every training and validation batch as the module received it."""
    record = RecordBatches()
    trainer = L.Trainer(max_epochs=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, default_root_dir=root, callbacks=[record],
                        num_sanity_val_steps=0)
    trainer.fit(create_policy("convnet", warmup_epochs=0, tbptt_steps=None), datamodule=dm)
    return record


def test_datamodule_mirrors_training_batches_only(tmp_path):
    path = write_dataset(tmp_path / "d.h5", [6, 9, 4, 7, 5])
    ds = TrajectoryDataset(path)
    dm = TrajectoryDataModule(path, batch_size=2, val_fraction=0.4, cache_mb=8, mirror_prob=1.0)
    record = record_batches(dm, tmp_path)
    assert record.train and record.val
    for batches, mirrored in ((record.train, True), (record.val, False)):
        for batch in batches:
            for i, m in enumerate(batch["traj_index"].tolist()):
                raw = ds[m]
                n = raw["depth"].shape[0]
                depth = raw["depth"].float()[:, None] / 255.0
                cmd, quat = raw["velocity_cmd"], raw["quat"]
                if mirrored:
                    depth, cmd = depth.flip(-1), cmd * torch.tensor([1.0, -1.0, 1.0])
                    quat = quat * torch.tensor([1.0, -1.0, 1.0, -1.0])
                torch.testing.assert_close(batch["depth"][i, :n], depth)
                torch.testing.assert_close(batch["velocity_cmd"][i, :n], cmd)
                torch.testing.assert_close(batch["quat"][i, :n], quat)


def test_bad_probability_is_one_line(tmp_path):
    with pytest.raises(VitflyError, match=r"data.mirror_prob: expected a probability in \[0, 1\], got 1.5"):
        TrajectoryDataModule(str(tmp_path / "x.h5"), mirror_prob=1.5)


def test_coins_drawn_on_the_host_mirror_a_batch_on_the_device_without_reading_it_back(tmp_path):
    """The datamodule draws a training batch's coins before the batch leaves the host; mirroring with them
    needs nothing back from the device: here a batch on the meta device (no data, only shapes), whose
    ``traj_index`` cannot be read (drawing the coins from it raises), is mirrored all the same."""
    coins = mirror_coins(torch.tensor([3, 1, 4]), torch.tensor([0, 8, 0]), 0.5, seed=0, epoch=2)
    batch = {"depth": torch.zeros(3, 5, 1, 6, 9), "quat": torch.zeros(3, 5, 4), "velocity_cmd": torch.zeros(3, 5, 3),
             "traj_index": torch.tensor([3, 1, 4]), "start": torch.tensor([0, 8, 0])}
    on_meta = {k: v.to("meta") for k, v in batch.items()}
    with pytest.raises(NotImplementedError):
        random_mirror(on_meta, 0.5, seed=0, epoch=2)
    mirrored = random_mirror(on_meta, 0.5, seed=0, epoch=2, coins=coins)
    assert mirrored["depth"].is_meta and mirrored["depth"].shape == (3, 5, 1, 6, 9)
    # through a real fit of 2 epochs at p = 0.5: each training item mirrored as its own coin (seed 0, its epoch,
    # trajectory and start) says, the coins drawn on the host before the trip
    path = write_dataset(tmp_path / "d.h5", [6, 9, 4, 7, 5])
    ds = TrajectoryDataset(path)
    had_coins = []

    class Watched(TrajectoryDataModule):  # what reaches the device side of the trip
        def on_after_batch_transfer(self, batch, dataloader_idx):
            had_coins.append(("mirror_host" in batch, self.trainer.training))
            return super().on_after_batch_transfer(batch, dataloader_idx)

    dm = Watched(path, batch_size=2, val_fraction=0.4, mirror_prob=0.5, split_seed=0)
    seen = []

    class Record(L.Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            seen.append((trainer.current_epoch, {k: v.clone() for k, v in batch.items()}))

    trainer = L.Trainer(max_epochs=2, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, default_root_dir=tmp_path, callbacks=[Record()],
                        num_sanity_val_steps=0)
    trainer.fit(create_policy("convnet", warmup_epochs=0, tbptt_steps=None), datamodule=dm)
    flips = []
    for epoch, got in seen:
        assert "mirror_host" not in got  # used up by the mirroring, not handed to the module
        expected = mirror_coins(got["traj_index"], torch.zeros_like(got["traj_index"]), 0.5, 0, epoch)
        for i, m in enumerate(got["traj_index"].tolist()):
            depth = ds[m]["depth"].float()[:, None] / 255.0
            n = depth.shape[0]
            flips.append(bool(expected[i]))
            torch.testing.assert_close(got["depth"][i, :n], depth.flip(-1) if expected[i] else depth)
    assert len(seen) == 4 and True in flips and False in flips  # 3 training trajectories, 2 batches, 2 epochs
    assert set(had_coins) == {(True, True), (False, False)}  # coins with every training batch, none in validation
