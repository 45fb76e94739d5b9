"""Dataset format v1: writer -> reader round trip, atomic writes, version and corruption errors."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from tesseract4d.dataset_format import (
    FORMAT_VERSION, CameraFrames, DatasetFormatError, DatasetInfo, Episode, episode_path, init_dataset,
    list_episode_files, read_episode, read_episode_attrs, read_info, remove_partial_files, write_episode,
)


def _episode(seed: int = 7, T: int = 5, H: int = 8, W: int = 10) -> Episode:
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(T, H, W, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    cams = {
        name: CameraFrames(
            rgb=rng.integers(0, 256, (T, H, W, 3), dtype=np.uint8),
            depth_m=rng.uniform(0.2, 2.0, (T, H, W)).astype(np.float32),
            normal_cam=n.astype(np.float32),
            K=np.tile(np.array([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]]), (T, 1, 1)),
            T_world_cam=np.tile(np.eye(4), (T, 1, 1)),
            segmentation=rng.integers(0, 5, (T, H, W)).astype(np.int32),
            seg_id_to_name={0: "background", 3: "cube"},
        )
        for name in ("close", "base_camera")
    }
    return Episode(
        env_id="PickCube-v1", seed=seed, instruction="lift the red cube", cameras=cams,
        frame_steps=np.arange(T, dtype=np.int32) * 3, actions=rng.normal(size=(3 * T, 8)).astype(np.float32),
        qpos=rng.normal(size=(T, 9)).astype(np.float32), object_poses={"cube": rng.normal(size=(T, 7)).astype(np.float32)},
        success=True, control_mode="pd_joint_pos", env_kwargs={"sim_backend": "physx_cpu"}, fps=4.0,
        metadata={"package_versions": {"sapien": "3.0.3"}},
    )


def test_round_trip(tmp_path):
    init_dataset(tmp_path, DatasetInfo(height=8, width=10, cameras=["close", "base_camera"]))
    ep = _episode()
    path = write_episode(tmp_path, ep)
    assert path == episode_path(tmp_path, "PickCube-v1", 7) and list_episode_files(tmp_path) == [path]
    back = read_episode(path)
    for name, cam in ep.cameras.items():
        got = back.cameras[name]
        np.testing.assert_array_equal(got.rgb, cam.rgb)
        np.testing.assert_array_equal(got.depth_m, cam.depth_m)
        np.testing.assert_allclose(got.normal_cam, cam.normal_cam, atol=1e-3)  # stored as float16
        np.testing.assert_array_equal(got.segmentation, cam.segmentation)
        np.testing.assert_array_equal(got.K, cam.K)
        np.testing.assert_array_equal(got.T_world_cam, cam.T_world_cam)
        assert got.seg_id_to_name == cam.seg_id_to_name
    np.testing.assert_array_equal(back.actions, ep.actions)
    np.testing.assert_array_equal(back.qpos, ep.qpos)
    np.testing.assert_array_equal(back.object_poses["cube"], ep.object_poses["cube"])
    np.testing.assert_array_equal(back.frame_steps, ep.frame_steps)
    assert (back.instruction, back.success, back.control_mode, back.env_kwargs, back.fps, back.metadata) == (
        ep.instruction, True, "pd_joint_pos", {"sim_backend": "physx_cpu"}, 4.0, ep.metadata)
    # Partial reads: one camera, a frame slice.
    part = read_episode(path, cameras=["close"], frames=slice(1, 3))
    assert list(part.cameras) == ["close"] and part.num_frames == 2
    np.testing.assert_array_equal(part.cameras["close"].rgb, ep.cameras["close"].rgb[1:3])
    attrs = read_episode_attrs(path)
    assert (attrs["num_frames"], attrs["height"], attrs["width"]) == (5, 8, 10)
    # Readable with h5py alone, chunked per frame and compressed.
    with h5py.File(path) as f:
        rgb = f["cameras/close/rgb"]
        assert rgb.chunks == (1, 8, 10, 3) and rgb.compression == "gzip"


def test_partial_files_never_count_and_are_removed(tmp_path):
    init_dataset(tmp_path, DatasetInfo(height=8, width=10))
    write_episode(tmp_path, _episode(seed=1))
    partial = tmp_path / "episodes/PickCube-v1/.seed_000002.deadbeef.partial.h5"
    partial.write_bytes(b"half an episode")
    assert [p.name for p in list_episode_files(tmp_path)] == ["seed_000001.h5"]
    assert remove_partial_files(tmp_path) == [partial] and not partial.exists()


def test_invalid_episode_is_refused_and_nothing_is_left(tmp_path):
    ep = _episode()
    ep.cameras["close"].depth_m = ep.cameras["close"].depth_m[:, :4]
    with pytest.raises(DatasetFormatError, match="depth_m must have shape"):
        write_episode(tmp_path, ep)
    assert not list((tmp_path).rglob("*.h5"))


def test_other_format_version_is_refused(tmp_path):
    (tmp_path / "info.json").write_text(json.dumps({"format_version": FORMAT_VERSION + 1}))
    with pytest.raises(DatasetFormatError, match=f"version {FORMAT_VERSION + 1}.*new folder"):
        init_dataset(tmp_path, DatasetInfo())
    with pytest.raises(DatasetFormatError, match="reads version"):
        read_info(tmp_path)


def test_truncated_shard_is_reported(tmp_path):
    init_dataset(tmp_path, DatasetInfo(height=8, width=10))
    path = write_episode(tmp_path, _episode())
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetFormatError, match="corrupt or truncated"):
        read_episode(path)
