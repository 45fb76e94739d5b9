"""The RGB-D-N autoencoder, its trainer and the latent cache, on a tiny random config (seconds)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tesseract4d import dataset_format as df
from tesseract4d.errors import UserError
from tesseract4d.model.autoencoder import (
    RGBDNAutoencoder, autoencoder_hash, get_autoencoder_preset, save_autoencoder,
)
from tesseract4d.model.autoencoder_loading import load_autoencoder
from tesseract4d.model.model_space import ModelSpace, channel_slices

from tesseract4d.testing.model_fixtures import sigterm_after_step
from tesseract4d.testing.synthetic_scene import synthetic_episode, write_segmented_dataset

def test_round_trip_shapes_metric_depth_and_unit_normals():
    torch.manual_seed(0)
    cfg = get_autoencoder_preset("ae-test")
    assert cfg.spatial_compression >= 8
    model = RGBDNAutoencoder(cfg).eval()
    ms = model.model_space
    ep = synthetic_episode(0, frames=4, size=32)
    cam = ep.cameras["close"]
    x = ms.encode(cam.rgb, cam.depth_m, cam.normal_cam)  # (4, 7, 32, 32)
    z = model.encode(x)
    assert tuple(z.shape) == (4, *cfg.latent_shape) == (4, 4, 4, 4)
    with torch.no_grad():
        y = model.decode(z)
    assert tuple(y.shape) == tuple(x.shape)
    assert float(y.abs().max()) <= 1.0
    rgb, depth_m, normal = ms.decode(y)
    assert rgb.dtype == np.uint8 and rgb.shape == (4, 32, 32, 3)
    hit = depth_m > 0
    assert np.all((depth_m[hit] >= ms.near_m - 1e-6) & (depth_m[hit] <= ms.far_m + 1e-6))
    n = y[:, channel_slices()["normal"]].norm(dim=1)  # (4, 32, 32), in the tensor itself
    assert torch.all(((n - 1.0).abs() < 1e-4) | (n == 0))
    length = np.linalg.norm(normal, axis=-1)
    assert np.all((np.abs(length - 1) < 1e-4) | (length == 0))
    # clips: (b, t, 7, H, W) -> (b, t, C, h, w) -> back
    zc = model.encode_clips(x[None].repeat(2, 1, 1, 1, 1), chunk=3)
    assert tuple(zc.shape) == (2, 4, *cfg.latent_shape)
    with torch.no_grad():
        assert tuple(model.decode_clips(zc).shape) == (2, 4, 7, 32, 32)


def test_renormalised_normals_are_unit_or_zero_with_finite_gradients():
    """Normals are scaled to unit length; too short ones (no hit) become 0, and even an exactly zero
    vector gives a finite gradient (the loss back-propagates through decoding)."""
    from tesseract4d.model.model_space import renormalize_normals

    s = channel_slices()["normal"]
    x = torch.zeros(1, 7, 2, 2)
    x[0, s, 0, 0] = torch.tensor([0.0, 0.0, 2.0])
    x[0, s, 0, 1] = torch.tensor([0.1, 0.0, 0.0])  # shorter than MIN_NORMAL_LENGTH
    x.requires_grad_(True)
    y = renormalize_normals(x)
    assert torch.allclose(y[0, s, 0, 0], torch.tensor([0.0, 0.0, 1.0]))
    assert torch.equal(y[0, s, 0, 1], torch.zeros(3)) and torch.equal(y[0, s, 1, 1], torch.zeros(3))
    assert torch.equal(y[0, :s.start], x[0, :s.start])
    y.sum().backward()
    assert torch.isfinite(x.grad).all()


def test_bf16_decode_keeps_the_output_layer_in_fp32_and_stays_close_to_fp32():
    """Under bf16 autocast (what the pipeline does on a CPU with native bf16) the shipped
    autoencoder decodes in fp32 output, within a stated tolerance of the fp32 decode; the fp32
    output layer survives the deep copy the trainer's EMA makes."""
    import copy

    from tesseract4d.model.checkpoint import V2_CHECKPOINT
    from tesseract4d.model.latent_checkpoint import AUTOENCODER_DIR

    model = load_autoencoder(V2_CHECKPOINT / AUTOENCODER_DIR)
    torch.manual_seed(0)
    z = torch.randn(8, *model.config.latent_shape)
    with torch.no_grad():
        ref = model.decode(z)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = model.decode(z)
            ema_low = copy.deepcopy(model).decode(z)
    assert low.dtype == torch.float32
    assert torch.equal(low, ema_low)
    s = channel_slices()
    depth_mm = (low[:, s["depth"]] - ref[:, s["depth"]]).abs().mean() * (model.model_space.far_m - model.model_space.near_m) / 2 * 1000
    cos = (low[:, s["normal"]] * ref[:, s["normal"]]).sum(1).clamp(-1, 1)
    # Measured: 1.4 mm and 0.30° (1.6° with the output layer in bf16 as well).
    assert float(depth_mm) < 3.0
    assert float(torch.rad2deg(torch.acos(cos)).mean()) < 0.6
    assert float((low[:, s["rgb"]] - ref[:, s["rgb"]]).abs().mean()) < 0.01


def test_decoder_goes_channels_last_after_the_latent_resolution_with_the_same_output():
    """The decoder runs channels-first at the latent resolution and channels-last from its first
    upsampling (a speed choice): the memory layout changes, the decoded frames do not."""
    model = RGBDNAutoencoder(get_autoencoder_preset("ae-test")).eval()
    plain = RGBDNAutoencoder(get_autoencoder_preset("ae-test")).eval()
    plain.load_state_dict(model.state_dict())
    plain.vae.decoder.up_blocks[0].upsamplers[0]._forward_pre_hooks.clear()  # the layout the input comes in

    layouts = {}
    decoder = model.vae.decoder
    decoder.mid_block.register_forward_hook(lambda m, a, out: layouts.setdefault("latent resolution", out))
    decoder.up_blocks[0].register_forward_hook(lambda m, a, out: layouts.setdefault("upsampled", out))
    torch.manual_seed(0)
    z = torch.randn(3, *model.config.latent_shape)
    with torch.no_grad():
        out, ref = model.decode(z), plain.decode(z)
    assert layouts["latent resolution"].is_contiguous()
    assert layouts["upsampled"].is_contiguous(memory_format=torch.channels_last)
    assert torch.allclose(out, ref, atol=1e-5)


def test_save_load_same_outputs_and_hash(tmp_path):
    torch.manual_seed(1)
    model = RGBDNAutoencoder(get_autoencoder_preset("ae-test")).eval()
    model.set_latent_stats(torch.full((4,), 0.1), torch.full((4,), 2.0))
    save_autoencoder(model, tmp_path / "ae")
    loaded = load_autoencoder(tmp_path / "ae")
    x = torch.rand(2, 7, 32, 32) * 2 - 1
    assert torch.equal(model.encode(x), loaded.encode(x))
    assert loaded.config.latent_std == [2.0] * 4
    h = autoencoder_hash(tmp_path / "ae")
    loaded.set_latent_stats(torch.zeros(4), torch.ones(4))
    save_autoencoder(loaded, tmp_path / "ae2")
    assert autoencoder_hash(tmp_path / "ae2") != h
    with pytest.raises(UserError, match="train-autoencoder"):
        load_autoencoder(tmp_path / "missing")


def _train_cfg(data, out, **kw):
    from tesseract4d.model.autoencoder_trainer import AutoencoderTrainConfig

    return AutoencoderTrainConfig(data=data, out=out, preset="ae-test", batch_size=2, warmup_steps=1,
                                  precision="fp32", quiet=True, **kw)


def test_trainer_resume_is_exact_and_gate_is_stored(tmp_path):
    from tesseract4d.evaluation.autoencoder_fidelity import fidelity_metrics
    from tesseract4d.model.autoencoder_trainer import AutoencoderTrainer, load_heldout_frames

    data = write_segmented_dataset(tmp_path / "data")
    full = AutoencoderTrainer(_train_cfg(data, tmp_path / "full", max_steps=4))
    full.train()
    first = AutoencoderTrainer(_train_cfg(data, tmp_path / "split", max_steps=2))
    first.train()
    second = AutoencoderTrainer(_train_cfg(data, tmp_path / "split", max_steps=4, resume=True))
    heldout = load_heldout_frames(data, second.model, 8)
    second.fidelity_fn = lambda m: fidelity_metrics(m, heldout)
    gate = second.train()
    for a, b in zip(full.model.state_dict().values(), second.model.state_dict().values()):
        if a.is_cuda:  # cuDNN's convolution gradients are not bit-reproducible: equal up to rounding
            assert (a - b).abs().max() < 1e-4
        else:
            assert torch.equal(a, b)
    saved = json.loads((tmp_path / "split" / "ae_train_config.json").read_text())
    assert saved["max_steps"] == 4 and saved["resume"] is True  # the config of the run as it continued
    stored = json.loads((tmp_path / "split" / "autoencoder" / "fidelity.json").read_text())
    assert stored["step"] == 4 and stored == json.loads(json.dumps(gate))
    for key in ("rgb_psnr_db", "object_rgb_psnr_db", "depth_mae_mm", "object_depth_mae_mm", "depth_abs_rel",
                "normal_mean_deg", "object_normal_mean_deg"):
        assert np.isfinite(stored[key]), key
    exported = load_autoencoder(tmp_path / "split" / "autoencoder")
    assert exported.config.latent_mean is not None and len(exported.config.latent_std) == 4
    with pytest.raises(UserError, match="--resume"):
        AutoencoderTrainer(_train_cfg(data, tmp_path / "split", max_steps=4))


def test_train_autoencoder_command_writes_the_gate_and_a_reconstruction_sheet(tmp_path, capsys):
    import imageio.v3 as iio

    from tesseract4d import cli

    data = write_segmented_dataset(tmp_path / "data", episodes=2)
    out = tmp_path / "run"
    assert cli.main(["train-autoencoder", "--data", str(data), "--heldout", str(data), "--out", str(out),
                     "--preset", "ae-test", "--max-steps", "2", "--batch-size", "2", "--set", "precision=fp32",
                     "--heldout-frames", "8", "--quiet"]) == 0
    assert json.loads((out / "autoencoder" / "fidelity.json").read_text())["step"] == 2
    assert capsys.readouterr().out.count("fidelity gate on 8 held-out frames (step 2;") == 1  # printed once
    sheet = iio.imread(out / "reconstructions.png")
    assert sheet.shape == (4 * 2 * 32, 3 * 32, 3)  # 4 frames x (truth, reconstruction), RGB | depth | normals
    assert sheet.std() > 0


def test_fine_tune_starts_from_an_exported_autoencoder_on_several_datasets(tmp_path):
    from tesseract4d.testing.synthetic_scene import synthetic_episode

    from tesseract4d.model.autoencoder_trainer import AutoencoderTrainer

    data = write_segmented_dataset(tmp_path / "data")
    base = AutoencoderTrainer(_train_cfg(data, tmp_path / "base", max_steps=3))
    base.train()
    other = tmp_path / "other"
    df.init_dataset(other, df.DatasetInfo(height=32, width=32, cameras=["close"]))
    ep = synthetic_episode(7, 8, 32)
    ep.cameras["close"].segmentation = np.where(np.isclose(ep.cameras["close"].depth_m, 0.5), 18, 17).astype(np.int32)
    ep.cameras["close"].seg_id_to_name = {0: "background", 17: "ground", 18: "cube"}
    df.write_episode(other, ep)
    ft = AutoencoderTrainer(_train_cfg([data, other], tmp_path / "ft", max_steps=1, frame_stride=2,
                                       init=tmp_path / "base" / "autoencoder"))
    assert len(ft.frames) == (3 * 8 + 8) // 2
    exported = load_autoencoder(tmp_path / "base" / "autoencoder")
    for k, v in exported.state_dict().items():
        assert torch.equal(ft.model.state_dict()[k].cpu(), v), k
    ft.train()
    saved = json.loads((tmp_path / "ft" / "ae_train_config.json").read_text())
    assert saved["data"] == [str(data), str(other)] and saved["init"].endswith("autoencoder")
    with pytest.raises(UserError, match="--frame-stride"):
        AutoencoderTrainer(_train_cfg(data, tmp_path / "bad", frame_stride=0))


def test_wrong_resolution_is_a_user_error(tmp_path):
    from tesseract4d.model.autoencoder_trainer import AutoencoderTrainer

    data = write_segmented_dataset(tmp_path / "data", episodes=1, size=64)
    with pytest.raises(UserError, match="--resolution 32"):
        AutoencoderTrainer(_train_cfg(data, tmp_path / "run"))


def test_loss_weights_robot_and_object_pixels_and_edges():
    from tesseract4d.model.autoencoder_trainer import AutoencoderTrainConfig, pixel_weights

    ms = ModelSpace()
    ep = synthetic_episode(0, frames=1, size=32)
    cam = ep.cameras["close"]
    x = ms.encode(cam.rgb, cam.depth_m, cam.normal_cam)
    mask = torch.from_numpy(np.isclose(cam.depth_m, 0.5))
    w = pixel_weights(x, mask, AutoencoderTrainConfig(object_weight=5.0, edge_weight=2.0))[:, 0]  # (1, 32, 32)
    inside = mask & ~torch.from_numpy(np.pad(~np.isclose(cam.depth_m[0], 0.5), 1, constant_values=True)[None, 2:, 1:-1])
    assert float(w[mask].max()) == pytest.approx(7.0)  # object pixel at the square's edge
    assert float(w[~mask].min()) == pytest.approx(1.0)  # plain scenery
    assert inside.any()


def test_an_autoencoder_config_with_the_removed_decoder_depth_reads_only_at_its_no_op_value():
    """Autoencoders saved before the lighter decoder was removed record ``decoder_layers_per_block``:
    null (or the encoder's depth) reads as before, a lighter one is refused with the fix."""
    from tesseract4d.errors import UserError
    from tesseract4d.model.autoencoder import AutoencoderConfig, get_autoencoder_preset

    saved = get_autoencoder_preset("ae-test").to_dict()
    for no_op in (None, saved["layers_per_block"]):
        assert AutoencoderConfig.from_dict({**saved, "decoder_layers_per_block": no_op}) == AutoencoderConfig.from_dict(saved)
    with pytest.raises(UserError, match="decoder of 0 layers per block"):
        AutoencoderConfig.from_dict({**saved, "decoder_layers_per_block": 0})


def test_gate_measures_edge_sharpness_of_the_round_trip(tmp_path):
    from tesseract4d.evaluation.autoencoder_fidelity import fidelity_metrics, format_fidelity, reconstruct_frames
    from tesseract4d.evaluation.believability import edge_sharpness
    from tesseract4d.model.autoencoder_trainer import load_heldout_frames

    data = write_segmented_dataset(tmp_path / "data", episodes=1)
    model = RGBDNAutoencoder(get_autoencoder_preset("ae-test"))
    frames = load_heldout_frames(data, model, 4)
    gate = fidelity_metrics(model, frames)
    truth_rgb, decoded_rgb = model.model_space.decode(frames.frames.float())[0], model.model_space.decode(reconstruct_frames(model, frames.frames))[0]
    # the held-out evaluation's measure of sharpness, on the round trip: the ceiling a latent model meets
    assert gate["rgb_edge_sharpness"] == pytest.approx(edge_sharpness(decoded_rgb, truth_rgb)) and gate["rgb_edge_sharpness"] > 0
    assert edge_sharpness(truth_rgb, truth_rgb) == pytest.approx(1.0)
    assert "RGB edge sharpness" in format_fidelity(gate)
    del gate["rgb_edge_sharpness"]  # a gate stored before it was measured still prints
    assert "RGB edge sharpness" not in format_fidelity(gate)


# --------------------------------------------------------------------------- latent cache


def test_latent_cache_reused_when_valid_rebuilt_when_autoencoder_changes(tmp_path):
    from tesseract4d.model.latent_cache import LatentClipDataset, ensure_latent_cache, open_latent_cache

    data = write_segmented_dataset(tmp_path / "data", episodes=2)
    torch.manual_seed(0)
    ae = RGBDNAutoencoder(get_autoencoder_preset("ae-test")).eval()
    save_autoencoder(ae, tmp_path / "ae_a")
    cache, built = ensure_latent_cache(data, tmp_path / "ae_a")
    assert built and len(cache.episodes) == 2
    lat = cache.episodes[0].latents
    assert tuple(lat.shape) == (8, 4, 4, 4) and lat.dtype == torch.float16
    x = ae.model_space.encode(*(getattr(df.read_episode(df.list_episode_files(data)[0]).cameras["close"], k)
                               for k in ("rgb", "depth_m", "normal_cam")))
    assert torch.allclose(lat.float(), ae.encode(x), atol=1e-2)
    assert float(cache.episodes[0].objects.max()) > 0  # the square is an object
    # ... and the scene's only object: its shares are those of the robot/object mask (no robot here)
    assert torch.equal(cache.episodes[0].scene_objects, cache.episodes[0].objects)
    mtime = (cache.folder / "latents.safetensors").stat().st_mtime_ns
    again, built = ensure_latent_cache(data, tmp_path / "ae_a")
    assert not built and (again.folder / "latents.safetensors").stat().st_mtime_ns == mtime
    # another autoencoder: open refuses, ensure rebuilds
    torch.manual_seed(1)
    save_autoencoder(RGBDNAutoencoder(get_autoencoder_preset("ae-test")), tmp_path / "ae_b")
    with pytest.raises(UserError, match="encode-latents"):
        open_latent_cache(cache.folder, tmp_path / "ae_b")
    (cache.folder / "notes.txt").write_text("the user's own notes")  # a rebuild replaces only the cache's files
    rebuilt, built = ensure_latent_cache(data, tmp_path / "ae_b")
    assert built and rebuilt.autoencoder_hash == autoencoder_hash(tmp_path / "ae_b")
    assert not torch.equal(rebuilt.episodes[0].latents, lat)
    assert (cache.folder / "notes.txt").read_text() == "the user's own notes"
    assert not list(cache.folder.parent.glob(".*tmp*"))
    clips = LatentClipDataset(rebuilt, num_frames=4)
    batch, texts, objects = clips.sample_batch(3, torch.Generator().manual_seed(0), with_objects=True)
    assert tuple(batch.shape) == (3, 4, 4, 4, 4) and len(texts) == 3 and tuple(objects.shape) == (3, 4, 2, 4, 4)
    assert clips.has_scene_objects and torch.equal(objects[:, :, 0], objects[:, :, 1])


def _strip_scene_objects(folder):
    """Rewrite a latent cache as it was written before it carried the scene objects' shares."""
    import json

    from safetensors.torch import load_file, save_file

    tensors = load_file(str(folder / "latents.safetensors"))
    save_file({k: v for k, v in tensors.items() if not k.endswith(".scene_objects")}, str(folder / "latents.safetensors"))
    meta = json.loads((folder / "cache.json").read_text())
    del meta["scene_objects"]
    (folder / "cache.json").write_text(json.dumps(meta))


def test_a_cache_without_scene_objects_is_rebuilt_beside_its_episodes_and_refused_for_their_weight_without(tmp_path):
    import shutil
    from types import SimpleNamespace

    from tesseract4d.model.latent_cache import LatentClipDataset, ensure_latent_cache
    from tesseract4d.model.recipe import check_scene_objects

    data = write_segmented_dataset(tmp_path / "data", episodes=2)
    torch.manual_seed(0)
    save_autoencoder(RGBDNAutoencoder(get_autoencoder_preset("ae-test")), tmp_path / "ae")
    cache, _ = ensure_latent_cache(data, tmp_path / "ae")
    _strip_scene_objects(cache.folder)
    rebuilt, built = ensure_latent_cache(data, tmp_path / "ae")  # the episodes are there: built anew, with them
    assert built and all(e.scene_objects is not None for e in rebuilt.episodes)
    # a cache that travelled without its episodes is used as it is; the weight that needs the shares says what to run
    travelled = tmp_path / "travelled"
    travelled.mkdir()
    shutil.copy(data / "info.json", travelled / "info.json")
    shutil.copytree(cache.folder, travelled / "latent_cache" / "close")
    _strip_scene_objects(travelled / "latent_cache" / "close")
    old, built = ensure_latent_cache(travelled, tmp_path / "ae")
    assert not built and old.episodes[0].scene_objects is None
    clips = LatentClipDataset(old, num_frames=4)
    assert not clips.has_scene_objects and not clips.objects(0)[:, 1].any()
    check_scene_objects(clips, SimpleNamespace(scene_object_weight=1.0))  # not asked for: fine
    with pytest.raises(UserError, match="encode-latents .*--rebuild"):
        check_scene_objects(clips, SimpleNamespace(scene_object_weight=8.0))


def test_latent_cache_outlives_a_decoder_swap_but_not_an_encoder_change(tmp_path):
    # A decoder-only fine-tune makes the same latents: its cache stays valid (here, there and travelling);
    # one changed encoder weight makes it another autoencoder's cache.
    import shutil

    from tesseract4d.model.autoencoder import latents_hash
    from tesseract4d.model.latent_cache import ensure_latent_cache, open_latent_cache

    data = write_segmented_dataset(tmp_path / "data", episodes=2)
    torch.manual_seed(0)
    ae = RGBDNAutoencoder(get_autoencoder_preset("ae-test")).eval()
    state = {k: v.half().float() for k, v in ae.state_dict().items()}
    save_autoencoder(ae, tmp_path / "ae", state_dict={k: v.half() for k, v in state.items()})  # shipped as float16
    cache, built = ensure_latent_cache(data, tmp_path / "ae")
    assert built and cache.meta["latents_hash"] == latents_hash(tmp_path / "ae")
    decoder_key = next(k for k in state if k.startswith("vae.decoder."))
    state[decoder_key] += 0.5
    save_autoencoder(ae, tmp_path / "new_decoder", state_dict=state)  # a fine-tune's float32 export
    assert autoencoder_hash(tmp_path / "new_decoder") != autoencoder_hash(tmp_path / "ae")
    reused, built = ensure_latent_cache(data, tmp_path / "new_decoder")
    assert not built and torch.equal(reused.episodes[0].latents, cache.episodes[0].latents)
    open_latent_cache(cache.folder, tmp_path / "new_decoder")  # no error
    copy = tmp_path / "copy"  # travelling without its episodes, as to a GPU machine
    copy.mkdir()
    shutil.copy(data / "info.json", copy / "info.json")
    shutil.copytree(cache.folder, copy / cache.folder.relative_to(data))
    _, built = ensure_latent_cache(copy, tmp_path / "new_decoder")
    assert not built
    encoder_key = next(k for k in state if k.startswith("vae.encoder."))
    state[encoder_key] += 0.5
    save_autoencoder(ae, tmp_path / "new_encoder", state_dict=state)
    assert latents_hash(tmp_path / "new_encoder") != latents_hash(tmp_path / "ae")
    with pytest.raises(UserError, match="encode-latents"):
        open_latent_cache(cache.folder, tmp_path / "new_encoder")
    _, built = ensure_latent_cache(data, tmp_path / "new_encoder")
    assert built


def test_latent_cache_travels_without_its_episodes(tmp_path):
    # A dataset folder copied with only info.json and its cache (e.g. to a GPU machine) trains from
    # the cache as it is, for the autoencoder that built it, and refuses another with the fix named.
    import shutil

    from tesseract4d.model.latent_cache import ensure_latent_cache

    data = write_segmented_dataset(tmp_path / "data", episodes=2)
    torch.manual_seed(0)
    save_autoencoder(RGBDNAutoencoder(get_autoencoder_preset("ae-test")), tmp_path / "ae")
    cache, _ = ensure_latent_cache(data, tmp_path / "ae")
    copy = tmp_path / "copy"
    copy.mkdir()
    shutil.copy(data / "info.json", copy / "info.json")
    shutil.copytree(cache.folder, copy / cache.folder.relative_to(data))
    moved, built = ensure_latent_cache(copy, tmp_path / "ae")
    assert not built and [e.instruction for e in moved.episodes] == [e.instruction for e in cache.episodes]
    assert all(torch.equal(a.latents, b.latents) for a, b in zip(moved.episodes, cache.episodes))
    torch.manual_seed(1)
    save_autoencoder(RGBDNAutoencoder(get_autoencoder_preset("ae-test")), tmp_path / "other")
    with pytest.raises(UserError, match="holds no episodes, only a latent cache"):
        ensure_latent_cache(copy, tmp_path / "other")


def test_latent_cache_never_writes_into_a_folder_that_is_not_a_cache(tmp_path):
    from tesseract4d.model.latent_cache import ensure_latent_cache

    data = write_segmented_dataset(tmp_path / "data", episodes=1)
    save_autoencoder(RGBDNAutoencoder(get_autoencoder_preset("ae-test")), tmp_path / "ae")
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "latents.safetensors").write_text("not ours")
    (theirs / "cache.json").write_text('{"format": "something else"}')
    before = {p.name: p.read_bytes() for p in theirs.iterdir()}
    with pytest.raises(UserError, match="is not a latent cache"):
        ensure_latent_cache(data, tmp_path / "ae", folder=theirs)
    assert {p.name: p.read_bytes() for p in theirs.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ae", "data", "theirs"]  # no temporary left behind


def test_latent_cache_rejects_other_resolution(tmp_path):
    from tesseract4d.model.latent_cache import ensure_latent_cache

    data = write_segmented_dataset(tmp_path / "data", episodes=1, size=64)
    save_autoencoder(RGBDNAutoencoder(get_autoencoder_preset("ae-test")), tmp_path / "ae")
    before = sorted(p.relative_to(data) for p in data.rglob("*"))
    with pytest.raises(UserError, match="--resolution 32"):
        ensure_latent_cache(data, tmp_path / "ae")
    assert sorted(p.relative_to(data) for p in data.rglob("*")) == before  # nothing left in the user's dataset


def test_trainer_never_takes_over_a_folder_it_did_not_write(tmp_path):
    from tesseract4d.model.autoencoder_trainer import AutoencoderTrainer

    data = write_segmented_dataset(tmp_path / "data", episodes=1)
    # A diffusion training run: checkpoint-XXXXXX folders, but not this trainer's.
    other = tmp_path / "other_run"
    (other / "checkpoint-000002").mkdir(parents=True)
    (other / "checkpoint-000002" / "state.json").write_text("{}")
    (other / "notes.txt").write_text("the user's own notes")
    before = sorted((p.relative_to(other).as_posix(), p.read_bytes() if p.is_file() else b"") for p in other.rglob("*"))
    with pytest.raises(UserError, match="--resume"):
        AutoencoderTrainer(_train_cfg(data, other, max_steps=1, resume=True))
    with pytest.raises(UserError, match="not empty"):
        AutoencoderTrainer(_train_cfg(data, other, max_steps=1))
    assert sorted((p.relative_to(other).as_posix(), p.read_bytes() if p.is_file() else b"")
                  for p in other.rglob("*")) == before
    # A new folder is claimed (marked as this trainer's) only once the inputs have loaded.
    AutoencoderTrainer(_train_cfg(data, tmp_path / "new", max_steps=1))
    assert (tmp_path / "new" / ".tesseract4d-output.json").is_file()


def test_max_steps_auto_fits_the_autoencoder_schedule_and_resume_keeps_it(tmp_path, monkeypatch):
    from tesseract4d.testing.model_fixtures import short_step_budget

    from tesseract4d.model.autoencoder_trainer import AutoencoderTrainer

    # Clock reads: start 1, after steps 1/2/3: 2, 3, 4 -> 1 step/s with 0.2 min - 3 s left.
    short_step_budget(monkeypatch, "tesseract4d.training.loop")
    fitted = 3 + int(1.0 * (12.0 - 3.0) * 0.93)
    data = write_segmented_dataset(tmp_path / "data")
    run = tmp_path / "auto"
    trainer = AutoencoderTrainer(_train_cfg(data, run, max_steps="auto", max_minutes=0.2))
    gate = trainer.train()
    assert trainer.step == fitted == gate["step"]
    saved = json.loads((run / "ae_train_config.json").read_text())
    assert saved["max_steps"] == fitted and saved["max_steps_fit"]["max_steps"] == fitted
    resumed = AutoencoderTrainer(_train_cfg(data, run, max_steps="auto", resume=True))
    resumed.load_checkpoint()
    assert resumed.cfg.max_steps == fitted and resumed.cfg.max_steps_fit == saved["max_steps_fit"]
    with pytest.raises(UserError, match="--max-minutes"):
        AutoencoderTrainer(_train_cfg(data, tmp_path / "nobudget", max_steps="auto"))


def test_a_stop_signal_ends_training_with_a_checkpoint_and_says_so(tmp_path, capsys, monkeypatch):
    """SIGTERM (a scheduler's stop; Ctrl-C is handled alike) during step 2 of 1,000: the trainer stops after the step, checkpoints and
    exports it, says why, and gives both signals their handlers back."""
    import signal

    from tesseract4d.model.autoencoder_trainer import AutoencoderTrainer

    data = write_segmented_dataset(tmp_path / "data")
    trainer = AutoencoderTrainer(_train_cfg(data, tmp_path / "run", max_steps=1000))
    sigterm_after_step(monkeypatch, trainer, 2)
    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    gate = trainer.train()
    assert {s: signal.getsignal(s) for s in before} == before
    assert gate["step"] == 2
    assert json.loads((tmp_path / "run" / "autoencoder" / "fidelity.json").read_text())["step"] == 2
    assert "stopped by SIGTERM at step 2; saving a checkpoint and the export" in capsys.readouterr().out
    assert trainer.stopped_by == signal.SIGTERM  # the command line then ends 143 (raise_for_stop)
