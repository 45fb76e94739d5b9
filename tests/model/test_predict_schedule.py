"""An instruction schedule reaches the model clip by clip, and a rollout streams its clips."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tesseract4d.testing.synthetic_scene import synthetic_episode

from tesseract4d.instruction_schedule import SCHEDULE_KEY, parse_schedule
from tesseract4d.model.predict import load_pipeline, predict_episode


@pytest.fixture(scope="module")
def pipe(micro_checkpoint):
    return load_pipeline(micro_checkpoint, precision="fp32")


def _texts_seen(pipe):
    """The text embeddings of every transformer call, recorded by a forward pre-hook."""
    seen: list[torch.Tensor] = []
    handle = pipe.transformer.register_forward_pre_hook(lambda module, args: seen.append(args[2].clone()))
    return seen, handle


def test_each_clip_is_sampled_with_its_segments_words(pipe):
    # micro clips are 8 frames: a 22-frame rollout is clips adding 1-7, 8-14, 15-21; "right" holds
    # 11-21, so most of clip 1 and all of clip 2.
    schedule = parse_schedule("0:push the square to the left;10:push the square to the right")
    first = synthetic_episode(2, frames=1)
    seen, handle = _texts_seen(pipe)
    try:
        ep = predict_episode(pipe, first, "push the square left, then right", num_frames=22, num_steps=2, seed=3,
                             schedule=schedule)
    finally:
        handle.remove()
    left, right = (pipe.text_encoder.encode([w]) for w in ("push the square to the left", "push the square to the right"))
    assert len(seen) == 3 * 2  # 3 clips x 2 steps, one pass each (the micro preset has no guidance)
    per_clip = [seen[2 * k] for k in range(3)]
    assert all(torch.equal(seen[2 * k], seen[2 * k + 1]) for k in range(3))
    assert torch.equal(per_clip[0], left) and torch.equal(per_clip[1], right) and torch.equal(per_clip[2], right)
    assert not torch.equal(left, right)
    assert ep.metadata["prediction"]["clip_instructions"] == [
        "push the square to the left", "push the square to the right", "push the square to the right"]
    assert [s["frame_start"] for s in ep.metadata[SCHEDULE_KEY]] == [0, 10]
    assert ep.instruction == "push the square left, then right" and ep.num_frames == 22

    # Without the schedule every clip gets the one instruction, and the frames after clip 0 differ.
    seen, handle = _texts_seen(pipe)
    try:
        plain = predict_episode(pipe, first, "push the square to the left", num_frames=22, num_steps=2, seed=3)
    finally:
        handle.remove()
    assert all(torch.equal(t, left) for t in seen)
    rgb, rgb_plain = ep.cameras["close"].rgb, plain.cameras["close"].rgb
    assert np.array_equal(rgb[:8], rgb_plain[:8]) and not np.array_equal(rgb[8:], rgb_plain[8:])


def test_the_rollout_streams_clip_by_clip(pipe):
    first = synthetic_episode(2, frames=1)
    streamed = []
    ep = predict_episode(pipe, first, "push the square to the right", num_frames=22, num_steps=2, seed=1,
                         on_clip=lambda k, so_far: streamed.append((k, so_far.cameras["close"].rgb.copy())))
    assert [k for k, _ in streamed] == [0, 1, 2]
    assert [len(rgb) for _, rgb in streamed] == [8, 15, 22]
    for _, rgb in streamed:  # every clip shown is the final rollout's beginning
        assert np.array_equal(rgb, ep.cameras["close"].rgb[:len(rgb)])


def test_predict_cli_follows_a_chained_episodes_schedule_or_the_users(micro_checkpoint, tmp_path, capsys):
    import dataclasses
    import json

    from tesseract4d import cli
    from tesseract4d import dataset_format as df

    schedule = parse_schedule("0:push the square to the left;12:push the square to the right")
    chained = synthetic_episode(0, frames=15)
    chained = dataclasses.replace(chained, instruction="push the square left, then right",
                                  metadata={SCHEDULE_KEY: [dataclasses.replace(s, frame_end=s.frame_end or 14).to_dict()
                                                           for s in schedule]})
    df.init_dataset(tmp_path / "data", df.DatasetInfo(height=32, width=32, cameras=["close"]))
    df.write_episode(tmp_path / "data", chained)
    out = tmp_path / "out"
    assert cli.main(["predict", "--checkpoint", str(micro_checkpoint), "--episode", f"{tmp_path / 'data'}/Synthetic-v0/0",
                     "--out", str(out), "--steps", "1"]) == 0
    ep = df.read_episode(df.resolve_episode(out))
    assert ep.num_frames == 15  # the chained episode's own length
    # clips add 1-7 and 8-14; frames 13-14 are "right", 8-12 "left": both clips follow the first words
    assert ep.metadata["prediction"]["clip_instructions"] == ["push the square to the left"] * 2
    assert "clip 2: frames 0-14 ready after" in capsys.readouterr().err

    out2 = tmp_path / "out2"
    assert cli.main(["predict", "--checkpoint", str(micro_checkpoint), "--episode", f"{tmp_path / 'data'}/Synthetic-v0/0",
                     "--out", str(out2), "--steps", "1", "--set", "schedule=0:push the square to the left;7:push the "
                     "square to the right", "--set", "num_frames=15"]) == 0
    ep2 = df.read_episode(df.resolve_episode(out2))
    assert ep2.metadata["prediction"]["clip_instructions"] == ["push the square to the left", "push the square to the right"]
    assert ep2.instruction == "push the square to the left, then push the square to the right"
    assert json.loads((out2 / "predict_config.json").read_text())["schedule"].startswith("0:push")
    assert cli.main(["predict", "--checkpoint", str(micro_checkpoint), "--episode", f"{tmp_path / 'data'}/Synthetic-v0/0",
                     "--out", str(tmp_path / "out3"), "--set", "schedule=5:push"]) == 2
    assert "must start at frame 0" in capsys.readouterr().err
