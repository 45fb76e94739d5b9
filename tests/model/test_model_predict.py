"""Prediction: checkpoint loading, seeded sampling, the predicted episode's contract, CLI, bad input."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from tesseract4d.testing.model_fixtures import MICRO
from tesseract4d.testing.synthetic_scene import synthetic_episode, write_synthetic_dataset

from tesseract4d import cli
from tesseract4d import dataset_format as df
from tesseract4d.errors import UserError
from tesseract4d.model.presets import PRESETS
from tesseract4d.model.predict import load_pipeline, predict_episode, predict_episodes, write_prediction


@pytest.fixture(scope="module")
def checkpoint(micro_preset, tmp_path_factory) -> Path:
    from tesseract4d.model.trainer import TrainConfig, Trainer

    root = tmp_path_factory.mktemp("model_predict")
    data = write_synthetic_dataset(root / "data", episodes=2)
    trainer = Trainer(TrainConfig(data=data, out=root / "run", preset=MICRO.name, max_steps=10, val_every=0,
                                  ckpt_every=0, quiet=True))
    return trainer.train()


@pytest.fixture(scope="module")
def pipe(checkpoint):
    return load_pipeline(checkpoint)


def _first_frame(preset) -> torch.Tensor:
    """A (1, 7, H, W) model-space first frame of seeded noise."""
    return torch.rand(1, 7, preset.height, preset.width, generator=torch.Generator().manual_seed(0)) * 2 - 1


def _push_right(pipe, first, steps: int, **kw) -> torch.Tensor:
    """One clip of "push the square to the right" from noise seed 4 (``kw``: sampler settings)."""
    return pipe(first, ["push the square to the right"], num_inference_steps=steps,
                generator=torch.Generator().manual_seed(4), **kw)


def test_load_pipeline_attributes(pipe, checkpoint):
    assert pipe.resolution == (32, 32) and pipe.num_frames == 8 and pipe.camera_name == "close"
    # Save -> load round trip: the loaded transformer holds the exported (EMA) weights exactly.
    from safetensors.torch import load_file

    saved = load_file(str(checkpoint / "transformer" / "diffusion_pytorch_model.safetensors"))
    loaded = pipe.transformer.state_dict()
    assert saved.keys() == loaded.keys() and all(torch.equal(saved[k], loaded[k]) for k in saved)


def test_seeded_sampling_is_deterministic(pipe):
    first = synthetic_episode(3, frames=1)
    a = predict_episode(pipe, first, "push the square to the right", seed=1, num_frames=8, num_steps=3)
    b = predict_episode(pipe, first, "push the square to the right", seed=1, num_frames=8, num_steps=3)
    c = predict_episode(pipe, first, "push the square to the right", seed=2, num_frames=8, num_steps=3)
    ca, cb, cc = (e.cameras["close"] for e in (a, b, c))
    assert np.array_equal(ca.rgb, cb.rgb) and np.array_equal(ca.depth_m, cb.depth_m)
    assert np.array_equal(ca.normal_cam, cb.normal_cam)
    assert not np.array_equal(ca.normal_cam[1:], cc.normal_cam[1:]) or not np.array_equal(ca.rgb[1:], cc.rgb[1:])
    # Batched samples: deterministic too, and different from each other.
    s1 = predict_episodes(pipe, first, "push", num_samples=2, seed=5, num_frames=8, num_steps=2)
    s2 = predict_episodes(pipe, first, "push", num_samples=2, seed=5, num_frames=8, num_steps=2)
    assert all(np.array_equal(x.cameras["close"].depth_m, y.cameras["close"].depth_m) for x, y in zip(s1, s2))
    assert not np.array_equal(s1[0].cameras["close"].depth_m[1:], s1[1].cameras["close"].depth_m[1:])


def test_predicted_episode_contract(pipe, tmp_path):
    first = synthetic_episode(4, frames=3)  # a longer episode: frame 0 is used
    calls = []
    ep = predict_episode(pipe, first, "push the square to the left", num_frames=19, num_steps=2,
                         progress=lambda step, total: calls.append((step, total)))
    # 19 frames = 3 clips of 8 (each continuing from the last frame), trimmed.
    assert calls[-1] == (6, 6) and len(calls) == 6
    cam = ep.cameras["close"]
    src = first.cameras["close"]
    assert cam.rgb.shape == (19, 32, 32, 3) and cam.rgb.dtype == np.uint8
    assert cam.depth_m.shape == (19, 32, 32) and cam.normal_cam.shape == (19, 32, 32, 3)
    assert np.array_equal(cam.rgb[0], src.rgb[0]) and np.array_equal(cam.depth_m[0], src.depth_m[0])
    assert np.allclose(cam.K, src.K[0]) and np.allclose(cam.T_world_cam, src.T_world_cam[0])
    assert (ep.env_id, ep.seed, ep.source, ep.instruction) == ("Synthetic-v0", 4, "prediction", "push the square to the left")
    from tesseract4d.model.predict import PREDICTED_CLIP_FPS

    assert ep.fps == PREDICTED_CLIP_FPS != first.fps  # the models' clip pace, not the first frame's recorded rate
    valid = cam.depth_m > 0
    assert ((cam.depth_m[valid] >= pipe.model_space.near_m) & (cam.depth_m[valid] <= pipe.model_space.far_m)).all()
    lengths = np.linalg.norm(cam.normal_cam, axis=-1)
    assert np.allclose(lengths[lengths > 0], 1.0, atol=1e-3)
    ep.validate()

    path = write_prediction(ep, tmp_path / "pred")
    assert path == df.episode_path(tmp_path / "pred", "Synthetic-v0", 4)
    back = df.read_episode(path)
    assert back.source == "prediction" and back.num_frames == 19
    assert np.array_equal(back.cameras["close"].rgb, cam.rgb)
    assert df.preview_path(tmp_path / "pred", "Synthetic-v0", 4).stat().st_size > 0
    assert df.read_info(tmp_path / "pred").source == "prediction"


def test_a_first_frame_at_a_whole_multiple_of_the_models_size_is_resized_for_it(pipe):
    """A 64² first frame for the 32² model: predicted from the frame as resize.py halves it (K halved),
    exactly as from that frame given at 32², the original size recorded."""
    from tesseract4d.resize import episode_at_resolution

    big = synthetic_episode(3, frames=1, size=64)
    pred = predict_episode(pipe, big, "push the square to the right", seed=1, num_steps=2)
    small = episode_at_resolution(big, "close", (32, 32))
    same = predict_episode(pipe, small, "push the square to the right", seed=1, num_steps=2)
    cam = pred.cameras["close"]
    assert cam.rgb.shape == (8, 32, 32, 3) and np.array_equal(cam.rgb, same.cameras["close"].rgb)
    assert np.allclose(cam.K[0], big.cameras["close"].K[0] * [[0.5], [0.5], [1]])
    assert pred.metadata["prediction"]["first_frame_resized_from"] == [64, 64]
    assert "first_frame_resized_from" not in same.metadata["prediction"]


def test_bad_inputs(pipe, checkpoint, tmp_path):
    first = synthetic_episode(0, frames=1)
    with pytest.raises(UserError, match="instruction is empty"):
        predict_episode(pipe, first, "   ")
    with pytest.raises(UserError, match="model predicts 32x32; it is resized for the model only by a whole factor"):
        predict_episode(pipe, synthetic_episode(0, frames=1, size=48), "push")
    with pytest.raises(UserError, match="not found"):
        load_pipeline(tmp_path / "missing")
    with pytest.raises(UserError, match="not a tesseract4d inference checkpoint"):
        load_pipeline(tmp_path)
    shutil.copytree(checkpoint, tmp_path / "run" / "final")  # a training run's folder, its export inside
    with pytest.raises(UserError, match=f"it is a training run folder: pass its export, --checkpoint {tmp_path / 'run' / 'final'}"):
        load_pipeline(tmp_path / "run")
    # A checkpoint whose weights belong to another preset.
    other = tmp_path / "other"
    shutil.copytree(checkpoint, other)
    cfg = json.loads((other / "tesseract4d_config.json").read_text())
    cfg["preset"] = PRESETS["tiny"].to_dict()
    (other / "tesseract4d_config.json").write_text(json.dumps(cfg))
    with pytest.raises(UserError, match="does not match preset 'tiny'"):
        load_pipeline(other)
    cfg["preset"]["name"] = "nonexistent"
    (other / "tesseract4d_config.json").write_text(json.dumps(cfg))
    with pytest.raises(UserError, match="unknown to this tesseract4d"):
        load_pipeline(other)


def test_predict_cli_episode_and_files(checkpoint, tmp_path, capsys):
    import imageio.v2 as imageio

    data = write_synthetic_dataset(tmp_path / "data", episodes=1)
    out = tmp_path / "out"
    assert cli.main(["predict", "--checkpoint", str(checkpoint), "--episode", f"{data}/Synthetic-v0/0",
                     "--out", str(out), "--steps", "2", "--num-frames", "8"]) == 0
    ep = df.read_episode(df.resolve_episode(out))
    assert ep.instruction == "push the square to the right" and ep.num_frames == 8
    assert json.loads((out / "predict_config.json").read_text())["steps"] == 2

    cam = synthetic_episode(0, frames=1).cameras["close"]
    imageio.imwrite(tmp_path / "rgb.png", cam.rgb[0])
    np.save(tmp_path / "depth.npy", cam.depth_m[0])
    np.savetxt(tmp_path / "K.txt", cam.K[0])
    out2 = tmp_path / "out2"
    assert cli.main(["predict", "--checkpoint", str(checkpoint), "--rgb", str(tmp_path / "rgb.png"), "--depth",
                     str(tmp_path / "depth.npy"), "--K", str(tmp_path / "K.txt"), "--instruction", "push left",
                     "--out", str(out2), "--steps", "1", "--num-samples", "2"]) == 0
    assert len(df.list_episode_files(out2 / "sample_00")) == 1 and len(df.list_episode_files(out2 / "sample_01")) == 1
    # Image files carry no segmentation: several draws follow the objects found by their colour (a red 5-px cube
    # on the plane), and a frame in which none stands out (the plane alone) samples one draw and says why.
    plane = np.broadcast_to(cam.rgb[0][:, :1], cam.rgb[0].shape).copy()
    cube = plane.copy()
    cube[12:17, 20:25] = (210, 40, 40)
    for name, rgb, out3 in (("cube", cube, tmp_path / "out3"), ("plane", plane, tmp_path / "out4")):
        imageio.imwrite(tmp_path / f"{name}.png", rgb)
        capsys.readouterr()
        assert cli.main(["predict", "--checkpoint", str(checkpoint), "--rgb", str(tmp_path / f"{name}.png"), "--depth",
                         str(tmp_path / "depth.npy"), "--K", str(tmp_path / "K.txt"), "--instruction", "push left",
                         "--out", str(out3), "--steps", "1", "--draws", "3"]) == 0
        said, draws = capsys.readouterr(), df.read_episode(df.resolve_episode(out3)).metadata["prediction"].get("draws")
        if name == "cube":
            assert draws["count"] == 3 and f"kept draw {draws['kept']} of 3" in said.out
        else:
            assert draws is None and "none was found in this first frame" in said.err

    assert cli.main(["predict", "--checkpoint", str(tmp_path / "missing"), "--episode", str(data),
                     "--out", str(tmp_path / "o3")]) == 2
    assert "not found" in capsys.readouterr().err
    assert cli.main(["predict", "--checkpoint", str(checkpoint), "--out", str(tmp_path / "o4")]) == 2
    assert "exactly one way" in capsys.readouterr().err


def test_frames_and_steps_default_to_the_checkpoint_preset(pipe):
    calls = []
    ep = predict_episode(pipe, synthetic_episode(5, frames=1), "push the square to the right",
                         progress=lambda step, total: calls.append((step, total)))
    assert ep.num_frames == MICRO.num_frames and calls[-1] == (MICRO.num_steps, MICRO.num_steps)


@pytest.mark.parametrize("text_guidance,image_guidance", [(2.0, 1.0), (2.0, 1.5)])
def test_batched_guidance_equals_the_separate_passes(checkpoint, text_guidance, image_guidance):
    """The sampler puts its conditional and unconditional passes into one forward; its guided
    prediction equals the one combined from a separate forward per pass."""
    from tesseract4d.model.codec import make_condition
    from tesseract4d.model.pipeline import guidance_passes

    pipe = load_pipeline(checkpoint, precision="fp32")
    p, g = pipe.preset, torch.Generator().manual_seed(0)
    first = pipe.codec.encode(torch.rand(2, 1, 7, p.height, p.width, generator=g) * 2 - 1)
    nt = pipe.codec.num_latent_frames(p.num_frames)
    cond = make_condition(first, nt, p.condition)
    null_cond = torch.zeros_like(cond)
    x = torch.randn((2, nt, *first.shape[2:]), generator=g)
    text = pipe.text_encoder.encode(["push the square to the left", "keep still"])
    null_text = torch.zeros_like(text)
    sigma = 0.6
    with torch.no_grad():
        batched = pipe._predict_x0(x, sigma, cond, null_cond, text, null_text, text_guidance, image_guidance)

        def one(c, t):
            return pipe.transformer(x, c, t, torch.full((2,), sigma)).float()

        full, img, none = one(cond, text), one(cond, null_text), one(null_cond, null_text)
    if image_guidance == 1.0:
        expected = img + text_guidance * (full - img)
    else:
        expected = none + image_guidance * (img - none) + text_guidance * (full - img)
    assert len(guidance_passes(text_guidance, image_guidance)) == (2 if image_guidance == 1.0 else 3)
    torch.testing.assert_close(batched, expected, atol=1e-4, rtol=1e-4)


def test_guidance_interval_guides_only_the_noisy_steps(checkpoint):
    """``guidance_min_sigma``: steps below it run one unguided pass; at 0 every step is guided, above 1
    none is (the clip of text guidance 1)."""
    pipe = load_pipeline(checkpoint, precision="fp32")
    p = pipe.preset
    first = _first_frame(p)
    batches = []
    hook = pipe.transformer.register_forward_pre_hook(lambda m, args: batches.append(args[0].shape[0]))

    def sample(**kw):
        batches.clear()
        clip = pipe(first, ["push the square to the left"], num_inference_steps=4, text_guidance=2.0,
                    generator=torch.Generator().manual_seed(3), **kw)
        return clip, list(batches)

    try:
        guided, n_guided = sample(guidance_min_sigma=0.0)
        default, _ = sample()
        half, n_half = sample(guidance_min_sigma=0.5)
        none, n_none = sample(guidance_min_sigma=1.5)
    finally:
        hook.remove()
    unguided = pipe(first, ["push the square to the left"], num_inference_steps=4, text_guidance=1.0,
                    generator=torch.Generator().manual_seed(3))
    assert p.guidance_min_sigma == 0.0 and torch.equal(default, guided)
    sigmas = [float(s) for s in pipe.scheduler.sigmas[:4]]  # 1, 0.667, 0.334, 0.001
    assert n_guided == [2, 2, 2, 2] and n_none == [1, 1, 1, 1]
    assert n_half == [2 if s >= 0.5 else 1 for s in sigmas] == [2, 2, 1, 1]
    torch.testing.assert_close(none, unguided)
    assert not torch.allclose(half, guided) and not torch.allclose(half, none)


def test_set_sampler_writes_a_copy_that_samples_with_the_new_settings(checkpoint, tmp_path, capsys):
    """set-sampler: the copy's weights are the checkpoint's byte for byte, its preset samples with the
    new settings (as the original does when given them), the change is recorded, the original is kept."""
    source = shutil.copytree(checkpoint, tmp_path / "source")
    (source / "MODEL_CARD.md").write_text("the source's card\n")
    before = {p.relative_to(source): p.read_bytes() for p in source.rglob("*") if p.is_file()}
    to = tmp_path / "interval"
    assert cli.main(["checkpoint", "set-sampler", "--checkpoint", str(source), "--to", str(to),
                     "--set", "guidance_min_sigma=0.5", "--text-guidance", "2"]) == 0
    assert {p.relative_to(source): p.read_bytes() for p in source.rglob("*") if p.is_file()} == before
    weights = Path("transformer") / "diffusion_pytorch_model.safetensors"
    assert (to / weights).read_bytes() == before[weights] and not (to / "MODEL_CARD.md").exists()
    config = json.loads((to / "tesseract4d_config.json").read_text())
    assert config["preset"]["guidance_min_sigma"] == 0.5 and config["preset"]["text_guidance"] == 2.0
    assert config["sampler_changed"] == [{"source": str(source), "previous": {"guidance_min_sigma": 0.0,
                                                                               "text_guidance": 1.0},
                                          "new": {"guidance_min_sigma": 0.5, "text_guidance": 2.0}}]
    copy, original = load_pipeline(to, precision="fp32"), load_pipeline(source, precision="fp32")
    assert copy.preset.guidance_min_sigma == 0.5 and original.preset.guidance_min_sigma == 0.0
    p = copy.preset
    first = _first_frame(p)

    def sample(pipe, **kw):
        return _push_right(pipe, first, 4, **kw)

    assert torch.equal(sample(copy), sample(original, text_guidance=2.0, guidance_min_sigma=0.5))
    assert not torch.equal(sample(copy), sample(original, text_guidance=2.0))  # the interval changes the clip


def test_set_sampler_refuses_bad_settings(checkpoint, tmp_path, capsys):
    runs = [(["--to", str(tmp_path / "a")], "nothing to change"),
            (["--to", str(tmp_path / "b"), "--set", "guidance_min_sigma=-0.1"], "--set guidance_min_sigma must be"),
            (["--to", str(tmp_path / "c"), "--text-guidance", "0"], "--text-guidance must be"),
            (["--to", str(tmp_path / "d"), "--steps", "0"], "--steps must be"),
            (["--to", str(tmp_path / "e"), "--set", "static_tolerance=-0.1"], "--set static_tolerance must be"),
            (["--to", str(tmp_path / "f"), "--set", "draws=0"], "--set draws must be a whole number of noise draws"),
            (["--to", str(checkpoint), "--steps", "3"], "--to")]
    for extra, message in runs:
        assert cli.main(["checkpoint", "set-sampler", "--checkpoint", str(checkpoint), *extra]) != 0
        assert message in capsys.readouterr().err
    assert not any((tmp_path / name).exists() for name in "abcdef")


def test_set_sampler_static_tolerance_keeps_the_first_frame_where_the_clip_is_still(checkpoint, tmp_path):
    """set-sampler --static-tolerance T: the copy samples as the original given T (the same clip as the
    original's where it moves by more than T, the given first frame where it stays within T / 2),
    frame 0 is the given first frame exactly, and a clip longer than one continues from such a frame."""
    from tesseract4d.model.static_composite import stillness

    to = tmp_path / "still"
    assert cli.main(["checkpoint", "set-sampler", "--checkpoint", str(checkpoint), "--to", str(to),
                     "--set", "static_tolerance=0.1"]) == 0
    copy, original = load_pipeline(to, precision="fp32"), load_pipeline(checkpoint, precision="fp32")
    assert copy.preset.static_tolerance == 0.1 and original.preset.static_tolerance == 0.0
    p = copy.preset
    first = _first_frame(p)

    def sample(pipe, **kw):
        return _push_right(pipe, first, 3, **kw)

    kept, plain = sample(copy), sample(original)
    assert torch.equal(kept, sample(original, static_tolerance=0.1)) and torch.equal(sample(copy, static_tolerance=0.0), plain)
    assert torch.equal(kept[:, 0], first) and not torch.equal(plain[:, 0], first)
    m = stillness(plain, 0.1)[:, :, None].expand_as(plain)
    assert (m == 1).any() and (m == 0).any()  # this clip has both
    assert torch.equal(kept[m == 1], first[:, None].expand_as(plain)[m == 1]) and torch.equal(kept[m == 0], plain[m == 0])
    longer = sample(copy, num_frames=2 * p.num_frames - 1)  # the second clip starts from frame 7, as composited
    assert torch.equal(longer[:, :p.num_frames], kept)
    with pytest.raises(ValueError, match="static_tolerance must be >= 0"):
        sample(copy, static_tolerance=-1.0)
