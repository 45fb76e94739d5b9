"""Self-forcing fine-tune (model/self_forcing.py): the cached condition is the frame a rollout hands to its
second clip, and the fine-tune trains on the condition it is given (self-forced or true)."""

from __future__ import annotations

import pytest
import torch

import dataclasses

from tesseract4d import dataset_format as df
from tesseract4d.errors import UserError
from tesseract4d.instruction_schedule import SCHEDULE_KEY, Segment
from tesseract4d.model.checkpoint import weights_digest
from tesseract4d.model.predict import load_pipeline
from tesseract4d.model.self_forcing import (
    SelfForcingConfig, SelfForcingTrainer, sample_self_forced, sampling_levels, self_forced_frames,
)
from tesseract4d.testing.synthetic_scene import synthetic_episode

LEFT, RIGHT = "push the square to the left", "push the square to the right"


def _chained_dataset(root, T, second_start):
    df.init_dataset(root, df.DatasetInfo(height=32, width=32, cameras=["close"]))
    for seed in (0, 1):
        ep = synthetic_episode(seed, frames=2 * T - 1)
        schedule = [Segment(LEFT, 0, second_start), Segment(RIGHT, second_start, 2 * T - 2)]
        df.write_episode(root, dataclasses.replace(ep, metadata={SCHEDULE_KEY: [x.to_dict() for x in schedule]}))
    df.write_episode(root, synthetic_episode(2, frames=2 * T - 1))  # one instruction: not a chain
    return root


def test_the_cache_holds_each_chain_s_own_clip_1_end_and_true_second_clip(micro_checkpoint, tmp_path):
    pipe = load_pipeline(micro_checkpoint, precision="fp32")
    T = pipe.num_frames
    data = _chained_dataset(tmp_path / "chains", T, T - 1)
    cache = sample_self_forced(micro_checkpoint, [data], noise_seed=0, precision="fp32", log=lambda m: None)
    assert cache["instructions"] == [(LEFT, RIGHT)] * 2 and cache["digest"] == weights_digest(micro_checkpoint)
    for i, f in enumerate(df.list_episode_files(data)[:2]):
        cam = df.read_episode(f).cameras["close"]
        frames = pipe.model_space.encode(cam.rgb, cam.depth_m, cam.normal_cam)
        torch.testing.assert_close(cache["true_condition"][i].float(), frames[T - 1], atol=1e-3, rtol=0)
        torch.testing.assert_close(cache["own_first"][i].float(), frames[0], atol=1e-3, rtol=0)
        torch.testing.assert_close(cache["target"][i].float(), pipe.codec.encode(frames[None, T - 1:])[0],
                                   atol=1e-2, rtol=0)  # the pixel codec: the true frames themselves
    assert not torch.equal(cache["self_condition"], cache["true_condition"])
    with pytest.raises(UserError, match="second clip"):
        sample_self_forced(micro_checkpoint, [_chained_dataset(tmp_path / "other", T, T - 3)], precision="fp32",
                           log=lambda m: None)


def test_the_cached_condition_is_the_frame_the_rollout_continues_from(micro_checkpoint):
    """The second clip of a two-clip rollout equals a clip sampled from the cached frame with the same noise."""
    pipe = load_pipeline(micro_checkpoint, precision="fp32")
    T = pipe.num_frames
    first = torch.rand(2, 7, *pipe.resolution) * 2 - 1
    w1, w2 = ["push the red cube left", "lift the cube"], ["lift the blue cylinder", "keep still"]
    noise = torch.randn(pipe.latent_shape(2), generator=torch.Generator().manual_seed(3))
    rollout = pipe(first, w1, num_frames=2 * T - 1, clip_instructions=[w1, w2], latents=noise,
                   generator=torch.Generator().manual_seed(5))
    cond, z = self_forced_frames(pipe, first, w1, noise, torch.Generator().manual_seed(5))
    assert torch.equal(cond, rollout[:, T - 1])
    assert z.shape == noise.shape
    # Clip 1 drew no noise of its own: clip 2's noise is the generator's first draw.
    noise2 = torch.randn(pipe.latent_shape(2), generator=torch.Generator().manual_seed(5))
    clip2 = pipe(cond, w2, latents=noise2, generator=torch.Generator().manual_seed(5))
    torch.testing.assert_close(clip2[:, 1:], rollout[:, T:], atol=1e-5, rtol=0)


def _write_cache(path, ckpt, pipe, perturb: float):
    g = torch.Generator().manual_seed(0)
    E, H, W = 3, *pipe.resolution
    true = torch.rand(E, 7, H, W, generator=g) * 2 - 1
    shape = pipe.latent_shape(E)
    torch.save({"episode_ids": [f"e{i}" for i in range(E)],
                "instructions": [("push the red cube left", "lift the blue cylinder")] * E,
                "self_condition": (true + perturb * torch.randn(E, 7, H, W, generator=g)).clamp(-1, 1).half(),
                "true_condition": true.half(), "target": torch.randn(shape, generator=g).half(),
                "own_first": true.half(), "own_noise": torch.randn(shape, generator=g).half(),
                "own_x0": torch.randn(shape, generator=g).half(), "checkpoint": str(ckpt),
                "digest": weights_digest(ckpt), "noise_seed": 0}, path)
    return path


def _trainer(tmp_path, ckpt, cache, condition, name, times="sampler"):
    cfg = SelfForcingConfig(teacher=ckpt, data=cache, out=tmp_path / name, condition=condition, own_share=0.5,
                            times=times, batch_size=4, max_steps=2, val_every=0, ckpt_every=0, quiet=True, precision="fp32")
    return SelfForcingTrainer(cfg)


def test_the_fine_tune_trains_on_the_condition_it_is_given(micro_checkpoint, tmp_path):
    pipe = load_pipeline(micro_checkpoint, precision="fp32")
    cache = _write_cache(tmp_path / "c.pt", micro_checkpoint, pipe, perturb=0.5)
    same = _write_cache(tmp_path / "same.pt", micro_checkpoint, pipe, perturb=0.0)
    own = _trainer(tmp_path, micro_checkpoint, cache, "self", "self")
    control = _trainer(tmp_path, micro_checkpoint, cache, "true", "true")
    x0, cond, texts, t, noise = own.batch(0)
    x0_c, cond_c, texts_c, t_c, noise_c = control.batch(0)
    # Same draws; only the second clips' condition differs (the own clip-1 pairs keep the true frame 0).
    assert torch.equal(x0, x0_c) and torch.equal(t, t_c) and torch.equal(noise, noise_c) and texts == texts_c
    assert not torch.equal(cond[:2], cond_c[:2]) and torch.equal(cond[2:], cond_c[2:])
    assert texts[:2] == ["lift the blue cylinder"] * 2 and texts[2:] == ["push the red cube left"] * 2
    levels = sampling_levels(own.preset.num_steps)
    assert all(any(abs(float(s) - float(v)) < 1e-6 for v in levels) for s in t[:2])
    with torch.no_grad():
        loss_self = float(own.compute_loss(0)[0])
        loss_true = float(control.compute_loss(0)[0])
        loss_same = float(_trainer(tmp_path, micro_checkpoint, same, "self", "same").compute_loss(0)[0])
    assert loss_self != pytest.approx(loss_true, rel=1e-4)  # the perturbed condition reaches the network
    assert loss_same == pytest.approx(loss_true, rel=1e-5)  # and nothing else differs between the two
    t_uniform = _trainer(tmp_path, micro_checkpoint, cache, "self", "uniform", times="uniform").batch(0)[3]
    assert not any(abs(float(s) - float(v)) < 1e-6 for s in t_uniform[:2] for v in levels)


def test_a_cache_of_other_weights_or_an_unknown_condition_is_refused(micro_checkpoint, tmp_path):
    pipe = load_pipeline(micro_checkpoint, precision="fp32")
    cache = _write_cache(tmp_path / "c.pt", micro_checkpoint, pipe, perturb=0.5)
    with pytest.raises(UserError, match="one of self, true"):
        _trainer(tmp_path, micro_checkpoint, cache, "given", "x")
    with pytest.raises(UserError, match="one of sampler, uniform"):
        _trainer(tmp_path, micro_checkpoint, cache, "self", "x", times="all")
    saved = torch.load(cache)
    saved["digest"] = "0" * 16
    torch.save(saved, tmp_path / "other.pt")
    with pytest.raises(UserError, match="other weights"):
        _trainer(tmp_path, micro_checkpoint, tmp_path / "other.pt", "self", "y")
