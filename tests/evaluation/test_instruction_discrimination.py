"""Instruction discrimination: the network's one-step prediction per instruction of a counterfactual
group, judged against the group's true futures (tesseract4d/evaluation/instruction_discrimination.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tesseract4d.testing.model_fixtures import MICRO
from tesseract4d.testing.synthetic_scene import synthetic_episode

from tesseract4d.evaluation.instruction_discrimination import (DISAGREE_SHARE, discrimination_errors, disagreement_mask,
                                                               one_step_predictions, own_closest,
                                                               sibling_sample_predictions, summarize_discrimination,
                                                               summarize_words_over_sample, words_over_sample)
from tesseract4d.model.predict import load_pipeline


def test_own_closest_is_a_strict_row_minimum_over_other_instructions():
    rng = np.random.default_rng(0)
    for _ in range(200):
        n = int(rng.integers(2, 6))
        errors = torch.from_numpy(rng.integers(0, 4, size=(n, n)).astype(np.float32))  # ties happen
        texts = [f"do {k}" for k in rng.integers(0, 3, size=n)]
        result = own_closest(errors, texts)
        for a in range(n):
            others = [j for j in range(n) if texts[j] != texts[a]]
            if not others:
                assert result[a] is None
            else:
                assert result[a] == all(errors[a, a] < errors[a, j] for j in others)


def test_a_prediction_that_ignores_the_words_discriminates_nothing():
    errors = torch.tensor([[1.0, 1.0, 1.0], [2.0, 2.0, 2.0], [0.5, 0.5, 0.5]])  # the same column for every instruction
    assert own_closest(errors, ["a", "b", "c"]) == [False, False, False]
    assert own_closest(torch.eye(3), ["a", "b", "c"]) == [False, False, False]  # each its own farthest
    assert own_closest(1 - torch.eye(3), ["a", "b", "c"]) == [True, True, True]


def test_summary_counts_and_chance():
    s = summarize_discrimination([(True, 4), (False, 4), (True, 2)])
    assert (s["episodes"], s["right"]) == (3, 2)
    assert s["share"] == pytest.approx(2 / 3) and s["chance"] == pytest.approx((0.25 + 0.25 + 0.5) / 3)
    assert 0 < s["wilson95"][0] < s["share"] < s["wilson95"][1] < 1
    assert summarize_discrimination([])["share"] is None


def test_disagreement_mask_picks_the_cells_where_futures_differ():
    x0 = torch.zeros(3, 4, 2, 10, 10)  # (n, t', c, h, w): futures agree everywhere but in one block
    x0[1, 2:, :, 3:5, 6:8] = 1.0
    x0[2, 2:, :, 3:5, 6:8] = -1.0
    mask = disagreement_mask(x0)
    assert mask.shape == (1, 4, 1, 10, 10)
    assert mask[0, 2:, 0, 3:5, 6:8].all()  # every disagreeing cell is in
    random = disagreement_mask(torch.randn(4, 4, 2, 10, 10))
    assert random.mean().item() == pytest.approx(DISAGREE_SHARE, abs=0.01)


@pytest.fixture(scope="module")
def pipe(micro_checkpoint):
    return load_pipeline(micro_checkpoint, precision="fp32")


def _group(pipe, n: int = 3):
    """n clips in model space (n, T, 7, H, W) (the square moving right, left, and another scene's
    square), their instructions, and shared noise."""
    episodes = [synthetic_episode(s, frames=MICRO.num_frames, direction=d) for s, d in ((0, 1), (0, -1), (1, 1))][:n]
    cams = [e.cameras["close"] for e in episodes]
    clips = torch.stack([pipe.model_space.encode(c.rgb, c.depth_m, c.normal_cam) for c in cams])
    texts = ["push the cube to the right", "push the cube to the left", "push the other cube"][:n]
    noise = torch.randn(pipe.latent_shape(1), generator=torch.Generator().manual_seed(3))
    return clips, texts, noise


def _without_words(pipe):
    """A copy of the pipeline whose network has its text projection zeroed: it sees every instruction alike."""
    import copy

    deaf = copy.copy(pipe)
    deaf.transformer = copy.deepcopy(pipe.transformer)
    with torch.no_grad():
        for p in deaf.transformer.backbone.patch_embed.text_proj.parameters():
            p.zero_()
    return deaf


def test_one_step_prediction_is_the_samplers_one_step_clip(pipe):
    """The measure looks at what the sampler's first step sees: one unguided Euler step from the
    scene's noise lands exactly on the network's prediction."""
    clips, texts, noise = _group(pipe)
    pred = one_step_predictions(pipe, clips, texts, noise)
    sampled = pipe(clips[:, 0], texts, num_inference_steps=1, text_guidance=1.0, image_guidance=1.0,
                   latents=noise.expand(len(texts), *noise.shape[1:]), output_type="latent")
    assert torch.allclose(pred, sampled, atol=1e-5)
    # Different words, different predictions: the micro network reads its text.
    assert not torch.allclose(pred[0], pred[2])


def test_errors_compare_every_prediction_with_every_true_future(pipe):
    clips, texts, noise = _group(pipe)
    errors = discrimination_errors(pipe, clips, texts, noise)
    assert errors.shape == (3, 3) and torch.isfinite(errors).all() and (errors >= 0).all()
    # Column j is prediction j: against a true future equal to another, its errors are equal too.
    same = discrimination_errors(pipe, clips[[0, 0, 2]], texts, noise)
    assert torch.allclose(same[0], same[1])


def test_a_network_without_words_discriminates_nothing(pipe):
    """With the text projection zeroed the network sees every instruction alike: no episode is
    discriminated, whatever the futures."""
    clips, texts, noise = _group(pipe, n=2)  # one scene (the same first frame), two futures
    deaf = _without_words(pipe)
    errors = discrimination_errors(deaf, clips, texts, noise)
    assert torch.allclose(errors, errors[:, :1].expand_as(errors))
    assert own_closest(errors, texts) == [False, False]


def test_sibling_sample_predictions_are_denoising_steps_from_each_others_noisy_samples(pipe):
    """P[a, j]: episode a's first frame and words, shown j's noisy sample at t; the diagonal is the
    ordinary denoising step, and an off-diagonal entry is the step a sampler would take had its sample
    drifted to j's future."""
    from tesseract4d.model.codec import make_condition

    clips, texts, noise = _group(pipe)
    t = 0.5
    pred = sibling_sample_predictions(pipe, clips, texts, noise, t)
    assert pred.shape[:2] == (3, 3)
    x0 = pipe.codec.encode(clips)
    cond = make_condition(pipe.codec.encode(clips[:, :1]), noise.shape[1], pipe.preset.condition)
    text = pipe.text_encoder.encode(texts)
    x_t = (1 - t) * x0[2:3] + t * noise  # episode 2's noisy sample, shown to episode 0
    direct = pipe._predict_x0(x_t, t, cond[:1], torch.zeros_like(cond[:1]), text[:1], torch.zeros_like(text[:1]), 1.0, 1.0)
    assert torch.allclose(pred[0, 2], direct[0], atol=1e-5)


def test_a_network_without_words_never_sides_with_them(pipe):
    """With the text projection zeroed, the words cannot make a's prediction from j's sample differ
    from j's own denoising step: the prediction depends on the sample and the (shared) first frame
    only."""
    clips, texts, noise = _group(pipe, n=2)  # one scene, two futures
    deaf = _without_words(pipe)
    pred = sibling_sample_predictions(deaf, clips, texts, noise)
    assert torch.allclose(pred[0], pred[1], atol=1e-6)  # row a does not depend on a's words
    judged = words_over_sample(deaf, clips, texts, noise)
    assert len(judged) == 2
    # Whatever the words say, the judgments come out the same: they are the sample's, not the words'.
    assert words_over_sample(deaf, clips, ["stay where you are", "wave at the camera"], noise) == judged


def test_words_over_sample_summary():
    s = summarize_words_over_sample([True, False, False, True])
    assert (s["pairs"], s["words"], s["share"], s["t"]) == (4, 2, 0.5, 0.5)
    assert summarize_words_over_sample([])["share"] is None
