"""The RGB-D-N network, model space, text encoder and presets: shapes, invariants, the 5B structure."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tesseract4d.testing.model_fixtures import micro_latent_preset, register_preset, write_tiny_cogvideox_folder
from tesseract4d.testing.synthetic_scene import synthetic_episode, write_synthetic_dataset

from tesseract4d.errors import UserError
from tesseract4d.model.model_space import MODALITY_CHANNELS, NUM_CHANNELS, ModelSpace, channel_slices
from tesseract4d.model.codec import PixelCodec, make_condition
from tesseract4d.model.rgbdn_transformer import RGBDNTransformer
from tesseract4d.model.presets import CONDITION_FIRST, CONDITION_REPEAT, PRESETS, get_preset


def test_model_space_round_trip():
    ep = synthetic_episode(0)
    cam = ep.cameras["close"]
    cam.depth_m[0, 0, 0] = 0.0  # no hit
    cam.depth_m[0, 0, 1] = 7.0  # beyond the range
    cam.normal_cam[0, 0, 0] = 0.0
    space = ModelSpace()
    x = space.encode(cam.rgb, cam.depth_m, cam.normal_cam)
    assert x.shape == (8, NUM_CHANNELS, 32, 32) and x.dtype == torch.float32
    assert float(x.abs().max()) <= 1.0
    rgb, depth, normal = space.decode(x)
    assert np.array_equal(rgb, cam.rgb)
    inside = (cam.depth_m > space.near_m) & (cam.depth_m < space.far_m * 0.98)
    assert np.abs(depth[inside] - cam.depth_m[inside]).max() < 1e-5
    assert depth[0, 0, 0] == 0.0 and depth[0, 0, 1] == 0.0  # no hit / beyond range decode to "no measurement"
    lengths = np.linalg.norm(normal, axis=-1)
    assert np.allclose(lengths[lengths > 0], 1.0, atol=1e-5) and lengths[0, 0, 0] == 0.0
    # Predicted normals off unit length are renormalised.
    x[:, channel_slices()["normal"]] *= 0.5
    assert np.allclose(np.linalg.norm(space.decode(x)[2], axis=-1)[inside], 1.0, atol=1e-5)


def test_presets_registry():
    assert {"tiny", "tiny-128", "cogvideox-5b"} <= set(PRESETS)
    tiny = get_preset("tiny")
    assert (tiny.height, tiny.width, tiny.num_frames, tiny.backbone["num_layers"]) == (64, 64, 16, 4)
    assert get_preset("tiny-128").height == 128
    with pytest.raises(UserError, match="unknown preset"):
        get_preset("huge")


@pytest.mark.parametrize("name", ["tiny", "tiny-128"])
def test_forward_shapes_pixel_presets(name):
    preset = get_preset(name)
    torch.manual_seed(0)
    model = RGBDNTransformer(dict(preset.backbone), dict(MODALITY_CHANNELS)).eval()
    x = torch.randn(1, preset.num_frames, NUM_CHANNELS, preset.height, preset.width)
    cond = make_condition(x[:, :1], preset.num_frames, preset.condition)
    text = torch.randn(1, preset.max_text_tokens, preset.backbone["text_embed_dim"])
    with torch.no_grad():
        out = model(x, cond, text, torch.tensor([0.5]))
    assert out.shape == x.shape and torch.isfinite(out).all()
    n_params = sum(p.numel() for p in model.parameters())
    if name == "tiny":
        assert n_params * 4 < 29e6  # the shipped fp32 export stays under 30 MB


def test_zero_init_depth_normal_inputs_do_not_change_output():
    """At initialisation the new depth/normal projections are zero: changing those inputs (noisy or
    condition) leaves every output, RGB included, unchanged."""
    preset = get_preset("tiny")
    torch.manual_seed(0)
    model = RGBDNTransformer(dict(preset.backbone), dict(MODALITY_CHANNELS)).eval()
    x = torch.randn(1, 16, NUM_CHANNELS, 64, 64)
    cond = x[:, :1].expand(-1, 16, -1, -1, -1).clone()
    text = torch.randn(1, 32, 384)
    t = torch.tensor([0.7])
    x2, cond2 = x.clone(), cond.clone()
    s = channel_slices()
    for part in (x2, cond2):
        part[:, :, s["depth"]] = torch.randn_like(part[:, :, s["depth"]])
        part[:, :, s["normal"]] = torch.randn_like(part[:, :, s["normal"]])
    with torch.no_grad():
        a = model(x, cond, text, t) - cond[:, :1]
        b = model(x2, cond2, text, t) - cond2[:, :1]
    assert torch.equal(a[:, :, s["rgb"]], b[:, :, s["rgb"]])
    assert torch.allclose(a, b, atol=1e-5)  # depth/normal corrections too (up to the rounding of + cond)
    # ... while RGB inputs do change it.
    x3 = x.clone()
    x3[:, :, s["rgb"]] += 0.5
    with torch.no_grad():
        assert not torch.allclose(model(x3, cond, text, t) - cond[:, :1], a)


def test_first_frame_condition_modes():
    first = torch.randn(2, 1, 7, 4, 4)
    rep = make_condition(first, 5, CONDITION_REPEAT)
    assert rep.shape == (2, 5, 7, 4, 4) and torch.equal(rep[:, 3], first[:, 0])
    fst = make_condition(first, 5, CONDITION_FIRST)
    assert torch.equal(fst[:, 0], first[:, 0]) and not fst[:, 1:].any()
    assert PixelCodec().encode(first) is first


def test_text_encoder_pads_and_caches(capfd):
    from tesseract4d.model.build import build_text_encoder

    enc = build_text_encoder(get_preset("tiny"))
    assert "Loading weights" not in capfd.readouterr().err  # no progress bar of its own in every command
    e = enc.encode(["pick up the red cube", "push the blue cube to the goal", "pick up the red cube"])
    assert e.shape == (3, 32, 384)
    assert torch.equal(e[0], e[2]) and not torch.equal(e[0], e[1])
    assert not e[0, 12:].any()  # padding is zero
    assert "pick up the red cube" in enc._cache


def test_cogvideox_5b_structure_from_local_folder(tmp_path, monkeypatch):
    """The 5B preset's code path with a tiny random CogVideoX-I2V folder: built through the local
    loader (VAE, T5, transformer with pretrained RGB weights), trained, exported, reloaded, sampled."""
    from tesseract4d.model.build import build_codec, build_transformer
    from tesseract4d.model.predict import load_pipeline, predict_episode
    from tesseract4d.model.trainer import TrainConfig, Trainer

    preset = register_preset(monkeypatch, micro_latent_preset())
    folder = write_tiny_cogvideox_folder(tmp_path / "pretrained")
    codec = build_codec(preset, folder)
    assert codec.modality_channels == {"rgb": 4, "depth": 4, "normal": 4}
    model = build_transformer(preset, codec, folder)
    from diffusers import CogVideoXTransformer3DModel

    original = CogVideoXTransformer3DModel.from_pretrained(folder / "transformer").state_dict()
    ours = model.state_dict()
    assert torch.equal(ours["backbone.patch_embed.proj.projs.rgb.weight"], original["patch_embed.proj.weight"])
    assert torch.equal(ours["backbone.proj_out.heads.depth.weight"], original["proj_out.weight"])
    assert not ours["backbone.patch_embed.proj.projs.normal.weight"].any()

    clip = torch.rand(1, 9, 7, 32, 32) * 2 - 1
    z = codec.encode(clip, generator=torch.Generator().manual_seed(0))
    assert z.shape == (1, 3, 12, 8, 8)
    assert codec.decode(z).shape == clip.shape
    cond = make_condition(z[:, :1], 3, preset.condition)
    with torch.no_grad():
        out = model(z, cond, torch.randn(1, 8, 32), torch.tensor([0.3]))
    assert out.shape == z.shape

    data = write_synthetic_dataset(tmp_path / "data", episodes=2, frames=9)
    final = Trainer(TrainConfig(data=data, out=tmp_path / "run", preset=preset.name, pretrained=folder, max_steps=1,
                                val_every=0, quiet=True)).train()
    pipe = load_pipeline(final)
    assert pipe.resolution == (32, 32) and pipe.num_frames == 9 and pipe.text_encoder.kind == "t5"
    ep = predict_episode(pipe, synthetic_episode(9, frames=1), "push the square", num_frames=9, num_steps=2)
    assert ep.cameras["close"].rgb.shape == (9, 32, 32, 3)

    with pytest.raises(UserError, match="--pretrained"):
        build_codec(preset, tmp_path / "nowhere")
