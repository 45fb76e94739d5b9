"""scripts/episodes_pack.py: episodes packed small for another machine and written back there as dataset
folders the project reads (the autoencoder trains from them)."""

from __future__ import annotations

import numpy as np
import pytest
from project_scripts import load_script
from synthetic_scene import write_grouped_dataset, write_segmented_dataset

from tesseract4d import dataset_format as df


def test_pack_unpack_round_trip_keeps_every_field_within_its_step(tmp_path):
    tool = load_script("episodes_pack")
    squares = write_segmented_dataset(tmp_path / "squares", episodes=3, frames=8)
    groups = write_grouped_dataset(tmp_path / "groups", scenes=2, frames=8)
    # A far depth beyond the stored range and a negative normal component, as rendered scenes have.
    path = df.list_episode_files(squares)[0]
    ep = df.read_episode(path)
    next(iter(ep.cameras.values())).depth_m[0, 0, 0] = 9.0
    df.write_episode(squares, ep)

    parts = tool.pack([squares, groups], tmp_path / "packed", frame_stride=2, part_mb=0.004)  # several parts
    assert len(parts) > 1 and all(p.with_suffix(".json").is_file() for p in parts)
    folders = tool.unpack(tmp_path / "packed", tmp_path / "there", workers=2)
    assert sorted(f.name for f in folders) == ["groups", "squares"]
    for src in (squares, groups):
        there = tmp_path / "there" / src.name
        assert df.read_info(there) == df.read_info(src)
        originals, copies = df.list_episode_files(src), df.list_episode_files(there)
        assert [p.name for p in originals] == [p.name for p in copies]
        for a_path, b_path in zip(originals, copies):
            a, b = df.read_episode(a_path, frames=slice(None, None, 2)), df.read_episode(b_path)
            for field in ("env_id", "seed", "instruction", "success", "control_mode", "env_kwargs", "fps", "source",
                          "metadata", "variant", "intent"):
                assert getattr(a, field) == getattr(b, field), field
            assert np.array_equal(a.frame_steps, b.frame_steps) and np.array_equal(a.actions, b.actions)
            assert np.array_equal(a.qpos, b.qpos)
            assert a.object_poses.keys() == b.object_poses.keys()
            assert all(np.array_equal(a.object_poses[k], b.object_poses[k]) for k in a.object_poses)
            for name, ca in a.cameras.items():
                cb = b.cameras[name]
                assert cb.rgb.shape[0] == 4  # every second of 8 frames
                assert np.array_equal(ca.rgb, cb.rgb) and np.array_equal(ca.segmentation, cb.segmentation)
                assert ca.seg_id_to_name == cb.seg_id_to_name and all(isinstance(k, int) for k in cb.seg_id_to_name)
                assert np.array_equal(ca.K, cb.K) and np.array_equal(ca.T_world_cam, cb.T_world_cam)
                far = np.minimum(ca.depth_m, 65535 * tool.DEPTH_STEP_M)
                assert np.abs(far - cb.depth_m).max() <= tool.DEPTH_STEP_M / 2 + 1e-6
                assert np.array_equal(ca.depth_m == 0, cb.depth_m == 0)
                assert np.abs(ca.normal_cam - cb.normal_cam).max() <= tool.NORMAL_STEP / 2 + 1e-3  # float16 on disk
    copy = df.read_episode(df.list_episode_files(tmp_path / "there" / "squares")[0])
    assert next(iter(copy.cameras.values())).depth_m[0, 0, 0] == np.float32(65535 * tool.DEPTH_STEP_M)


def test_pack_spreads_a_subset_and_refuses_a_used_folder(tmp_path):
    tool = load_script("episodes_pack")
    data = write_segmented_dataset(tmp_path / "data", episodes=5, frames=4)
    tool.pack([data], tmp_path / "packed", episodes=3)
    (folder,) = tool.unpack(tmp_path / "packed", tmp_path / "there", workers=1)
    names = [p.name for p in df.list_episode_files(folder)]
    every = [p.name for p in df.list_episode_files(data)]
    assert names == [every[0], every[2], every[4]]
    with pytest.raises(SystemExit, match="not empty"):
        tool.pack([data], tmp_path / "packed")


def test_first_frame_pack_keeps_what_reflow_pairs_read(tmp_path):
    # distill's pairs read an episode's first frame and instruction (its groups from the ids): the copy has
    # those, every frame being the first, in fewer bytes than the whole episodes.
    from tesseract4d.model.clips import ClipDataset
    from tesseract4d.model.model_space import ModelSpace

    tool = load_script("episodes_pack")
    data = write_grouped_dataset(tmp_path / "groups", scenes=2, frames=8)
    whole = tool.pack([data], tmp_path / "whole")
    first = tool.pack([data], tmp_path / "first", first_frame=True)
    assert first[0].stat().st_size < whole[0].stat().st_size
    (there,) = tool.unpack(tmp_path / "first", tmp_path / "there", workers=1)
    kw = dict(num_frames=8, height=32, width=32, model_space=ModelSpace())
    a, b = ClipDataset(data, **kw), ClipDataset(there, **kw)
    assert [s.episode_id for s in a.sources] == [s.episode_id for s in b.sources]
    for i in range(len(a)):
        clip_a, text_a = a.clip(i)
        clip_b, text_b = b.clip(i)
        assert text_a == text_b and clip_b.shape == clip_a.shape
        assert (clip_b - clip_b[:1]).abs().max() == 0  # every frame the first
        assert (clip_b[0] - clip_a[0]).abs().max() < 0.02  # the first frame, within the depth/normal steps


def test_unpack_never_replaces_an_episode_file(tmp_path):
    # Unpacked over the originals, the quantised copies would replace them: refused before anything is written.
    tool = load_script("episodes_pack")
    data = write_segmented_dataset(tmp_path / "data", episodes=2, frames=4)
    before = {p: p.read_bytes() for p in df.list_episode_files(data)}
    tool.pack([data], tmp_path / "packed")
    with pytest.raises(SystemExit, match="exist already"):
        tool.unpack(tmp_path / "packed", tmp_path, workers=1)
    assert {p: p.read_bytes() for p in df.list_episode_files(data)} == before
    tool.unpack(tmp_path / "packed", tmp_path / "there", workers=1)
    with pytest.raises(SystemExit, match="exist already"):  # a second unpack of the same parts
        tool.unpack(tmp_path / "packed", tmp_path / "there", workers=1)
