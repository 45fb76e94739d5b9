"""Batched prediction of many scenes (predict_scenes): one prediction per scene, independent of
the batch size, each episode carrying its own scene; and of one scene under several instructions
from the same noise (predict_counterfactuals)."""

from __future__ import annotations

import numpy as np
import pytest
from tesseract4d.testing.synthetic_scene import synthetic_episode

from tesseract4d.errors import UserError
from tesseract4d.model.predict import load_pipeline, predict_counterfactuals, predict_episode, predict_scenes


@pytest.fixture(scope="module")
def pipe(micro_checkpoint):
    return load_pipeline(micro_checkpoint, precision="fp32")


def test_scenes_do_not_depend_on_batch_size(pipe):
    scenes = [synthetic_episode(s, frames=1, direction=1 if s % 2 else -1) for s in range(3)]
    texts = [e.instruction for e in scenes]
    calls = []
    one = predict_scenes(pipe, scenes, texts, batch_size=1, seed=4, num_steps=3)
    batched = predict_scenes(pipe, scenes, texts, batch_size=2, seed=4, num_steps=3,
                             progress=lambda s, t: calls.append((s, t)))
    assert calls[-1] == (6, 6) and len(calls) == 6  # 2 calls x 3 steps
    assert len(one) == len(batched) == 3
    for scene, a, b in zip(scenes, one, batched):
        ca, cb = a.cameras["close"], b.cameras["close"]
        assert (a.seed, a.instruction) == (scene.seed, scene.instruction) == (b.seed, b.instruction)
        assert np.array_equal(ca.rgb[0], scene.cameras["close"].rgb[0])
        # Same noise per scene; only the rounding of batched fp32 maths may differ.
        assert np.abs(ca.rgb.astype(int) - cb.rgb.astype(int)).max() <= 1
        assert np.allclose(ca.depth_m, cb.depth_m, atol=1e-4)
    # Different scenes give different futures.
    assert not np.array_equal(one[0].cameras["close"].rgb[1:], one[1].cameras["close"].rgb[1:])
    # The same seed again: the same predictions.
    again = predict_scenes(pipe, scenes, texts, batch_size=2, seed=4, num_steps=3)
    assert all(np.array_equal(x.cameras["close"].depth_m, y.cameras["close"].depth_m) for x, y in zip(batched, again))


def test_a_noise_seed_draws_what_predict_episode_draws(pipe):
    """The held-out evaluation batches scenes with noise_seeds=[seed] * n: each scene is then
    predicted exactly as predict_episode predicts it alone (one scene per call: bit for bit)."""
    from tesseract4d.model.predict import predict_episode

    scenes = [synthetic_episode(s, frames=1, direction=1 if s % 2 else -1) for s in range(2)]
    texts = [e.instruction for e in scenes]
    batched = predict_scenes(pipe, scenes, texts, batch_size=1, seed=5, num_steps=2, noise_seeds=[5, 5])
    for scene, text, pred in zip(scenes, texts, batched):
        alone = predict_episode(pipe, scene, text, seed=5, num_steps=2)
        assert np.array_equal(alone.cameras["close"].rgb, pred.cameras["close"].rgb)
        assert np.array_equal(alone.cameras["close"].depth_m, pred.cameras["close"].depth_m)
    with pytest.raises(UserError, match="one per scene"):
        predict_scenes(pipe, scenes, texts, noise_seeds=[5])


def test_bad_scene_inputs(pipe):
    scene = synthetic_episode(0, frames=1)
    with pytest.raises(UserError, match="one of each"):
        predict_scenes(pipe, [scene, scene], ["push"])
    with pytest.raises(UserError, match="at least 1"):
        predict_scenes(pipe, [scene], ["push"], batch_size=0)
    with pytest.raises(UserError, match="empty"):
        predict_scenes(pipe, [scene], [" "])
    with pytest.raises(UserError, match="32x32"):
        predict_scenes(pipe, [synthetic_episode(0, frames=1, size=48)], ["push"])


def test_counterfactuals_share_the_noise_and_differ_by_the_words(pipe):
    scene = synthetic_episode(5, frames=1)
    texts = ["push the square to the left", "push the square to the right"]
    pair = predict_counterfactuals(pipe, scene, texts, seed=7, num_steps=3)
    assert [e.instruction for e in pair] == texts and all(e.seed == scene.seed for e in pair)
    a, b = (e.cameras["close"] for e in pair)
    assert np.array_equal(a.rgb[0], b.rgb[0])  # the same first frame
    assert not np.array_equal(a.rgb[1:], b.rgb[1:])  # different words, different futures
    # Each future is what the instruction alone gives with that seed (batched rounding aside).
    for text, batched in zip(texts, (a, b)):
        alone = predict_episode(pipe, scene, text, seed=7, num_steps=3).cameras["close"]
        assert np.abs(alone.rgb.astype(int) - batched.rgb.astype(int)).max() <= 1
        assert np.allclose(alone.depth_m, batched.depth_m, atol=1e-4)
    with pytest.raises(UserError, match="at least one"):
        predict_counterfactuals(pipe, scene, [])
