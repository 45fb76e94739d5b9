"""The decoder that reads the first frame (model/first_frame_decoder.py): it starts as the shipped decoder,
its first-frame path changes what it draws (and the pipeline feeds it the given frame), it keeps the latent
space (the decoder swap takes it and refuses another encoder), and the shipped checkpoints predict with it."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tesseract4d.errors import UserError
from tesseract4d.model.autoencoder import (
    get_autoencoder_preset, latents_hash, RGBDNAutoencoder, save_autoencoder,
)
from tesseract4d.model.autoencoder_loading import load_autoencoder
from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT, V2_CHECKPOINT
from tesseract4d.model.first_frame_decoder import FIRST_FRAME_PREFIX, INJECTIONS, FirstFrameAutoencoder, from_autoencoder

from tesseract4d.testing.synthetic_scene import synthetic_episode, write_segmented_dataset

SHIPPED_AE = V2_CHECKPOINT / "autoencoder"


def _frames(size: int, seed: int = 0, frames: int = 4) -> torch.Tensor:
    from tesseract4d.model.model_space import ModelSpace

    cam = synthetic_episode(seed, frames, size).cameras["close"]
    return ModelSpace().encode(cam.rgb, cam.depth_m, cam.normal_cam)  # (T, 7, H, W)


def _perturb_path(model: FirstFrameAutoencoder, scale: float = 0.05) -> None:
    """Give the first-frame path non-zero output layers (as training does)."""
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for name, p in model.first_frame.named_parameters():
            if name.split(".")[-2] in ("conv_out", "proj"):
                p.copy_(torch.randn(p.shape, generator=g) * scale)


@pytest.mark.parametrize("injection", INJECTIONS)
def test_a_fresh_first_frame_decoder_decodes_exactly_as_the_shipped_one(injection):
    base = load_autoencoder(SHIPPED_AE)
    model = from_autoencoder(base, injection).eval()
    x = _frames(128)
    z = base.encode(x)
    with torch.no_grad():
        plain = base.decode_clips(z[None])
        read = model.decode_clips(z[None], first_frame=_frames(128, seed=3)[:1])  # any first frame: path is zero
    assert torch.equal(plain, read)
    assert torch.equal(base.encode(x), model.encode(x))  # the same encoder: the same latents


@pytest.mark.parametrize("injection", INJECTIONS)
def test_the_first_frame_path_changes_the_decoded_clip(injection):
    torch.manual_seed(0)
    base = RGBDNAutoencoder(get_autoencoder_preset("ae-test")).eval()
    model = from_autoencoder(base, injection).eval()
    _perturb_path(model)
    x = _frames(32)
    z = model.encode(x)[None]  # (1, T, C, h, w)
    with torch.no_grad():
        own = model.decode_clips(z, first_frame=x[:1])
        other = model.decode_clips(z, first_frame=_frames(32, seed=4)[:1])
        plain = base.decode_clips(z)
    # A decoder that ignored its first frame would give the same clip for both, and the base's.
    assert (own - other).abs().mean() > 1e-3
    assert (own - plain).abs().mean() > 1e-3


def test_save_load_keeps_the_path_and_the_latent_identity(tmp_path):
    torch.manual_seed(0)
    base = RGBDNAutoencoder(get_autoencoder_preset("ae-test")).eval()
    save_autoencoder(base, tmp_path / "base")
    model = from_autoencoder(base, "attention").eval()
    _perturb_path(model)
    save_autoencoder(model, tmp_path / "ff")
    loaded = load_autoencoder(tmp_path / "ff")
    assert isinstance(loaded, FirstFrameAutoencoder) and loaded.config.first_frame_injection == "attention"
    x = _frames(32)
    z = model.encode(x)[None]
    with torch.no_grad():
        assert torch.equal(model.decode_clips(z, first_frame=x[:1]), loaded.decode_clips(z, first_frame=x[:1]))
    assert latents_hash(tmp_path / "ff") == latents_hash(tmp_path / "base")
    keys = json.loads((tmp_path / "ff" / "config.json").read_text())
    assert keys["first_frame_injection"] == "attention"


def test_an_unknown_injection_is_a_user_error():
    base = RGBDNAutoencoder(get_autoencoder_preset("ae-test"))
    with pytest.raises(UserError, match="concat, attention"):
        from_autoencoder(base, "film")


@pytest.fixture(scope="module")
def swapped(tmp_path_factory):
    """The shipped v2 with a first-frame decoder whose path is not zero, swapped in with `swap-decoder`."""
    from tesseract4d.model.checkpoint_copies import replace_decoder

    root = tmp_path_factory.mktemp("swap")
    model = from_autoencoder(load_autoencoder(SHIPPED_AE), "concat").eval()
    _perturb_path(model, scale=0.02)
    save_autoencoder(model, root / "ff")
    return replace_decoder(V2_CHECKPOINT, root / "ff", root / "v2_ff"), root


def test_the_swap_keeps_the_latent_space(swapped):
    from tesseract4d.model.checkpoint import read_inference_config

    to, _ = swapped
    config = read_inference_config(to)
    assert latents_hash(to / "autoencoder") == latents_hash(SHIPPED_AE)
    assert config["autoencoder"]["trained_with_hash"] == read_inference_config(V2_CHECKPOINT)["autoencoder"]["hash"]
    assert isinstance(load_autoencoder(to / "autoencoder"), FirstFrameAutoencoder)


def test_the_swap_refuses_a_first_frame_decoder_with_another_encoder(tmp_path):
    from tesseract4d.model.checkpoint_copies import replace_decoder

    model = from_autoencoder(load_autoencoder(SHIPPED_AE), "concat")
    with torch.no_grad():
        model.vae.encoder.conv_in.weight.add_(1e-3)
    save_autoencoder(model, tmp_path / "ff_other")
    with pytest.raises(UserError, match="does not encode like"):
        replace_decoder(V2_CHECKPOINT, tmp_path / "ff_other", tmp_path / "to")
    assert not (tmp_path / "to").exists()


@pytest.mark.parametrize("student", [False, True], ids=["v2", "v2-2step"])
def test_the_shipped_checkpoints_load_and_predict_with_the_new_decoder(swapped, student):
    """The transformer of v2 (and of its 2-step student, which shares v2's latent space) predicts with the
    swapped decoder; the pipeline hands the decoder the given first frame: the predicted clip is the
    returned latents decoded with that frame, not with another."""
    from tesseract4d.model.checkpoint_copies import replace_decoder
    from tesseract4d.model.predict import load_pipeline

    to, root = swapped
    if student:
        to = replace_decoder(SHIPPED_CHECKPOINT, root / "ff", root / "v2_2step_ff")
    pipe = load_pipeline(to, precision="fp32")
    assert pipe.codec.reads_first_frame
    first = _frames(128)[:1]  # (1, 7, H, W)
    text = ["push the cube to the right"]
    # static_tolerance=0: no compositing of the given frame over still pixels, so the clip is the decoder's alone
    clip = pipe(first, text, num_inference_steps=1, static_tolerance=0.0, generator=torch.Generator().manual_seed(0))
    assert clip.shape == (1, pipe.num_frames, 7, 128, 128) and torch.isfinite(clip).all()
    z = pipe(first, text, num_inference_steps=1, generator=torch.Generator().manual_seed(0), output_type="latent")
    with_given = pipe.decode(z, first_frame=first)
    with_other = pipe.decode(z, first_frame=_frames(128, seed=4)[:1])
    assert (clip - with_given).abs().amax() < 1e-4
    assert (with_given - with_other).abs().mean() > 1e-4


def test_training_steps_export_a_first_frame_autoencoder_and_resume(tmp_path):
    from tesseract4d.model.first_frame_decoder_training import FirstFrameTrainConfig, train

    torch.manual_seed(0)
    base = RGBDNAutoencoder(get_autoencoder_preset("ae-test")).eval()
    save_autoencoder(base, tmp_path / "base")
    data = write_segmented_dataset(tmp_path / "data", episodes=2, frames=6, size=32)
    cfg = FirstFrameTrainConfig(data=[data], out=tmp_path / "run", init=tmp_path / "base", injection="concat+copy",
                                max_steps=2, warmup_steps=1, frames_per_clip=2, ckpt_every=1, precision="fp32",
                                permanence_loss=1.0)
    export = train(cfg, log=lambda m: None)
    model = load_autoencoder(export)
    assert isinstance(model, FirstFrameAutoencoder)
    assert latents_hash(export) == latents_hash(tmp_path / "base")
    out_weights = {k for k in model.state_dict() if k.startswith(FIRST_FRAME_PREFIX)}
    assert out_weights and any(model.state_dict()[k].abs().sum() > 0 for k in out_weights if "conv_out" in k)
    state = torch.load(tmp_path / "run" / "state.pt")
    assert state["step"] == 2
    cfg.max_steps = 3
    train(cfg, log=lambda m: None)
    assert torch.load(tmp_path / "run" / "state.pt")["step"] == 3
    history = torch.load(tmp_path / "run" / "state.pt")["history"]
    assert np.isfinite([h["loss"] for h in history]).all() and all(np.isfinite(h["lost"]) for h in history)


def test_training_refuses_an_out_holding_files_it_did_not_write(tmp_path):
    from tesseract4d.model.first_frame_decoder_training import STATE_FILE, FirstFrameTrainConfig, train

    out = tmp_path / "mine"
    out.mkdir()
    (out / STATE_FILE).write_bytes(b"a user's file")  # the name the trainer would read and replace
    cfg = FirstFrameTrainConfig(data=[tmp_path / "data"], out=out, init=tmp_path / "base", injection="concat")
    with pytest.raises(UserError, match="did not write"):
        train(cfg, log=lambda *_: None)
    assert (out / STATE_FILE).read_bytes() == b"a user's file" and sorted(p.name for p in out.iterdir()) == [STATE_FILE]


def test_the_copy_term_changes_the_clip_and_at_gate_one_draws_the_given_frame():
    from tesseract4d.model.model_space import renormalize_normals

    torch.manual_seed(0)
    base = RGBDNAutoencoder(get_autoencoder_preset("ae-test")).eval()
    model = from_autoencoder(base, "attention+copy").eval()
    copy = model.first_frame[-1].copy
    x = _frames(32)
    other = _frames(32, seed=4)[:1]
    z = model.encode(x)[None]  # (1, T, C, h, w)
    with torch.no_grad():
        plain = base.decode_clips(z)
        torch.nn.init.normal_(copy.weight, std=0.05)  # only the copy gate moves
        gated = model.decode_clips(z, first_frame=other)
        torch.nn.init.zeros_(copy.weight)
        torch.nn.init.ones_(copy.bias)  # gate 1 everywhere: the output is the given frame's pixels
        copied = model.decode_clips(z, first_frame=other)
    assert (gated - plain).abs().mean() > 1e-3
    expected = renormalize_normals(other.clamp(-1.0, 1.0))
    assert torch.allclose(copied[0], expected.expand_as(copied[0]), atol=1e-5)


def test_the_lost_object_loss_charges_each_lost_object_alike_and_spares_small_errors():
    from tesseract4d.model.first_frame_decoder_training import lost_object_loss
    from tesseract4d.object_colours import OBJECT_COLOUR_TOL

    target = torch.zeros(1, 3, 16, 16)
    objects = torch.zeros(1, 16, 16, dtype=torch.uint8)
    objects[0, 1:3, 1:3] = 1  # a 4-pixel cube
    objects[0, 6:14, 6:14] = 2  # a 64-pixel one
    target[:, 0][objects > 0] = 1.0  # both red on a grey table
    margin = OBJECT_COLOUR_TOL / 2
    assert float(lost_object_loss(target, target, objects, margin)) == pytest.approx(0.0, abs=1e-3)
    near = target + 10.0 / 127.5 / 3 ** 0.5  # every pixel 10 RGB units off: inside the margin
    assert float(lost_object_loss(near, target, objects, margin)) == pytest.approx(0.0, abs=1e-3)
    lose_small, lose_large = target.clone(), target.clone()
    lose_small[:, 0][objects == 1] = 0.0
    lose_large[:, 0][objects == 2] = 0.0
    small = lost_object_loss(lose_small.requires_grad_(), target, objects, margin)
    large = lost_object_loss(lose_large, target, objects, margin)
    assert float(small.detach()) == pytest.approx(float(large)) and float(small.detach()) == pytest.approx((127.5 - margin) / OBJECT_COLOUR_TOL / 2)
    small.backward()
    # A second copy where an object stood in frame 0 (a ghost on the vacated pixels) is charged as well.
    vacated = torch.zeros(1, 16, 16, dtype=torch.bool)
    vacated[0, 1:3, 5:7] = True
    ghost = target.clone()
    ghost[:, 0][vacated] = 1.0
    assert float(lost_object_loss(target, target, objects, margin, vacated)) == pytest.approx(0.0, abs=1e-3)
    assert float(lost_object_loss(ghost, target, objects, margin, vacated)) == pytest.approx((127.5 - margin) / OBJECT_COLOUR_TOL / 3)
    assert lose_small.grad[:, 0][objects == 1].abs().min() > 0 and lose_small.grad[:, 0][objects == 0].abs().max() == 0


@pytest.mark.parametrize("injection", ["concat+copy", "attention+copy"])
def test_the_4x_preset_takes_a_first_frame_decoder_that_starts_as_it(injection):
    import dataclasses

    config = get_autoencoder_preset("ae-f4c8")
    assert config.spatial_compression == 4 and config.latent_shape == (8, 32, 32)
    torch.manual_seed(0)
    small = dataclasses.replace(config, block_out_channels=(8, 16), norm_num_groups=4, height=32, width=32)
    base = RGBDNAutoencoder(small).eval()
    model = from_autoencoder(base, injection).eval()
    x = _frames(32)
    z = base.encode(x)[None]
    with torch.no_grad():
        assert torch.equal(base.decode_clips(z), model.decode_clips(z, first_frame=x[:1]))
        _perturb_path(model)
        assert (model.decode_clips(z, first_frame=x[:1]) - base.decode_clips(z)).abs().mean() > 1e-3


def test_a_trained_first_frame_decoder_goes_on_with_its_path_and_refuses_another_injection():
    torch.manual_seed(0)
    base = RGBDNAutoencoder(get_autoencoder_preset("ae-test")).eval()
    trained = from_autoencoder(base, "attention+copy").eval()
    _perturb_path(trained)
    again = from_autoencoder(trained, "attention+copy").eval()
    assert again.config.name == trained.config.name
    x = _frames(32)
    z = trained.encode(x)[None]
    with torch.no_grad():
        assert torch.equal(trained.decode_clips(z, first_frame=x[:1]), again.decode_clips(z, first_frame=x[:1]))
    with pytest.raises(UserError, match="does not fit"):
        from_autoencoder(trained, "concat")
