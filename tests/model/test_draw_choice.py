"""The best of several noise draws (tesseract4d/model/draw_choice.py): the score of how well a clip
keeps the first frame's objects in their colours, the choice among draws, and the sampler that uses
it (`set-sampler --draws N`) on a micro checkpoint."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from tesseract4d.testing.synthetic_scene import _segment, synthetic_episode

from tesseract4d import cli
from tesseract4d.model.draw_choice import WINDOW_PX, choose, draw_noise_seed, object_windows, objects_kept


def square_scene(frames: int = 8):
    """The synthetic moving square (id 18, 'cube'; 8 px, 1 px a frame, rows 19-26 and columns 14-21
    in frame 0) on a grey plane ('ground'), 96²: (episode, its camera, windows)."""
    ep = _segment(synthetic_episode(3, frames=frames, size=96))
    cam = ep.cameras["close"]
    return ep, cam, object_windows(cam.rgb[0], cam.segmentation[0], cam.seg_id_to_name)


def test_the_true_clip_keeps_its_object_and_a_fading_or_recoloured_one_loses_it_frame_by_frame():
    ep, cam, windows = square_scene()
    assert len(windows) == 1  # the square; the ground is not a scene object
    assert objects_kept(windows, cam.rgb) == 1.0  # it moves 1 px a frame, whole and in its colour
    square = cam.segmentation == 18
    plane = np.broadcast_to(cam.rgb[:, :, :1], cam.rgb.shape)  # column 0: the plane's grey of each row
    faded = cam.rgb.copy()
    faded[3:][square[3:]] = plane[3:][square[3:]]  # gone from frame 3: kept in frames 1 and 2 of 7
    assert objects_kept(windows, faded) == pytest.approx(2 / 7)
    recoloured = cam.rgb.copy()
    recoloured[5:][square[5:]] = 0  # another colour from frame 5: kept in 4 of 7
    assert objects_kept(windows, recoloured) == pytest.approx(4 / 7)
    # Moved whole within the window (WINDOW_PX around its first box): kept; far out of it: lost.
    colour = cam.rgb[0][square[0]][0]
    near, far = faded.copy(), faded.copy()
    near[3:, 19 + WINDOW_PX - 8:19 + WINDOW_PX, 14:22] = colour
    far[3:, 70:78, 70:78] = colour
    assert objects_kept(windows, near) == 1.0
    assert objects_kept(windows, far) == pytest.approx(2 / 7)


def test_a_scene_without_objects_or_frames_cannot_be_scored_and_keeps_draw_0():
    ep, cam, windows = square_scene()
    ground_only = object_windows(cam.rgb[0], np.full_like(cam.segmentation[0], 17), cam.seg_id_to_name)
    assert ground_only == [] and np.isnan(objects_kept(ground_only, cam.rgb))
    assert np.isnan(objects_kept(windows, cam.rgb[:1]))  # only the first frame: nothing predicted
    assert choose(ground_only, [cam.rgb, cam.rgb]) == (0, [pytest.approx(np.nan, nan_ok=True)] * 2)


def test_choose_keeps_the_highest_score_and_the_earliest_draw_on_a_tie():
    ep, cam, windows = square_scene()
    square = cam.segmentation == 18
    faded = cam.rgb.copy()
    faded[1:][square[1:]] = 0
    kept, scores = choose(windows, [faded, cam.rgb, cam.rgb.copy()])
    assert kept == 1 and scores[0] == 0.0 and scores[1] == scores[2] == 1.0


def test_draw_0_is_the_single_draw_and_other_draws_have_their_own_seeds():
    for seed in (0, 7, 2**61 + 5):
        assert draw_noise_seed(seed, 0) == seed
        others = [draw_noise_seed(seed, k) for k in range(1, 9)]
        assert len(set(others + [seed])) == 9 and all(0 <= s < 2**62 for s in others)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_the_score_of_any_clip_is_between_0_and_1(seed):
    ep, cam, windows = square_scene()
    clip = np.random.default_rng(seed).integers(0, 256, cam.rgb.shape, dtype=np.uint8)
    clip[0] = cam.rgb[0]
    assert 0.0 <= objects_kept(windows, clip) <= 1.0


@pytest.fixture(scope="module")
def draws_checkpoint(micro_checkpoint, tmp_path_factory):
    to = tmp_path_factory.mktemp("draws") / "best_of_3"
    assert cli.main(["checkpoint", "set-sampler", "--checkpoint", str(micro_checkpoint), "--to", str(to),
                     "--set", "draws=3"]) == 0
    return to


def test_the_kept_future_is_the_single_draw_of_its_noise_with_every_draw_scored(draws_checkpoint, micro_checkpoint):
    """A copy with --draws 3 samples 3 noises per future (3 times the steps) and keeps the one its score
    ranks first: exactly the future a single draw from that noise gives; the original samples one."""
    from tesseract4d.model.predict import load_pipeline, predict_episode

    pipe, original = load_pipeline(draws_checkpoint, precision="fp32"), load_pipeline(micro_checkpoint, precision="fp32")
    assert pipe.preset.draws == 3 and original.preset.draws == 1
    first = _segment(synthetic_episode(5, frames=1, size=32))
    steps = []
    kept = predict_episode(pipe, first, "push the square to the right", seed=2, num_steps=2,
                           progress=lambda s, t: steps.append((s, t)))
    info = kept.metadata["prediction"]["draws"]
    assert info["count"] == 3 and len(info["objects_kept"]) == 3 and steps[-1] == (6, 6)
    k = info["kept"]
    assert info["objects_kept"][k] == max(info["objects_kept"])
    single = predict_episode(original, first, "push the square to the right", seed=draw_noise_seed(2, k), num_steps=2)
    assert "draws" not in single.metadata["prediction"]
    assert np.array_equal(kept.cameras["close"].rgb, single.cameras["close"].rgb)
    assert np.array_equal(kept.cameras["close"].depth_m, single.cameras["close"].depth_m)
    cam = first.cameras["close"]
    windows = object_windows(cam.rgb[0], cam.segmentation[0], cam.seg_id_to_name)
    assert info["objects_kept"][k] == pytest.approx(objects_kept(windows, single.cameras["close"].rgb))
    # draws=1 overrides the preset: the first draw, unscored.
    one = predict_episode(pipe, first, "push the square to the right", seed=2, num_steps=2, draws=1)
    assert "draws" not in one.metadata["prediction"]
    assert np.array_equal(one.cameras["close"].rgb, predict_episode(original, first, "push the square to the right",
                                                                     seed=2, num_steps=2).cameras["close"].rgb)


def test_several_samples_of_one_first_frame_find_its_objects_once(draws_checkpoint, monkeypatch):
    """`predict --num-samples N` with draws: every sample keeps its best draw, scored against the objects
    of the one first frame they share, which are read from it once, not N times."""
    from tesseract4d.model import predict
    from tesseract4d.model.predict import load_pipeline, predict_episodes

    reads = []
    monkeypatch.setattr(predict, "object_windows", lambda *a: reads.append(a) or object_windows(*a))
    pipe = load_pipeline(draws_checkpoint, precision="fp32")
    first = _segment(synthetic_episode(5, frames=1, size=32))
    samples = predict_episodes(pipe, first, "push the square to the right", num_samples=3, seed=2, num_steps=2)
    assert len(reads) == 1 and len(samples) == 3
    assert all(s.metadata["prediction"]["draws"]["count"] == 3 for s in samples)
    assert len({s.cameras["close"].rgb[1:].tobytes() for s in samples}) == 3  # three different futures


def test_a_first_frame_without_segmentation_is_scored_by_the_objects_its_colours_show(draws_checkpoint):
    """Image files, the closed loop's observations and reconstructions carry no segmentation: their
    objects are found by colour (object_finder.py). A red cube on the grey plane is followed, as the
    segmentation would name it; a frame in which nothing stands out samples one draw."""
    from tesseract4d.errors import UserError
    from tesseract4d.model.predict import load_pipeline, predict_episode

    pipe = load_pipeline(draws_checkpoint, precision="fp32")
    ep = synthetic_episode(5, frames=1, size=32)
    cam = ep.cameras["close"]
    cam.rgb[0] = np.broadcast_to(cam.rgb[0][:, :1], cam.rgb[0].shape)  # the plane alone (its grey of each row)
    cam.rgb[0, 12:17, 20:25] = (210, 40, 40)
    assert cam.segmentation is None
    found = object_windows(cam.rgb[0])
    named = np.zeros((32, 32), np.int32)
    named[12:17, 20:25] = 18
    assert len(found) == 1 and found[0][1:] == object_windows(cam.rgb[0], named, {18: "cube"})[0][1:]
    kept = predict_episode(pipe, ep, "push", seed=2, num_steps=2)
    assert kept.metadata["prediction"]["draws"]["count"] == 3
    cam.rgb[0, 12:17, 20:25] = cam.rgb[0, 12:17, :5]
    assert object_windows(cam.rgb[0]) == []
    steps = []
    one = predict_episode(pipe, ep, "push", seed=2, num_steps=2, progress=lambda s, t: steps.append((s, t)))
    assert "draws" not in one.metadata["prediction"] and steps[-1] == (2, 2)
    with pytest.raises(UserError, match="--draws must be at least 1"):
        predict_episode(pipe, ep, "push", num_steps=2, draws=0)
