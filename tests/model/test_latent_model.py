"""The latent world model: the latent-128 preset's shapes, a micro latent model that overfits one
clip, checkpoint save -> load -> identical samples, and the bad-input errors (seconds each)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from tesseract4d import dataset_format as df
from tesseract4d.errors import UserError
from tesseract4d.model.autoencoder import RGBDNAutoencoder, get_autoencoder_preset, save_autoencoder
from tesseract4d.model.presets import AUTOENCODER, CONDITION_REPEAT, PRESETS, ModelPreset, get_preset

from tesseract4d.testing.synthetic_scene import write_segmented_dataset

MICRO_LATENT = ModelPreset(
    "micro-latent", AUTOENCODER, 32, 32, 8, CONDITION_REPEAT, "minilm", 8,
    backbone=dict(num_attention_heads=2, attention_head_dim=16, num_layers=2, time_embed_dim=32, text_embed_dim=384,
                  max_text_seq_length=8, sample_width=4, sample_height=4, sample_frames=8, patch_size=1,
                  patch_size_t=1, temporal_compression_ratio=1, use_rotary_positional_embeddings=True,
                  use_learned_positional_embeddings=False),
    lr=3e-3, warmup_steps=5, batch_size=2, ema_decay=0.9, text_dropout=0.0, image_dropout=0.0,
    num_steps=4, text_guidance=1.0, image_guidance=1.0,
)


@pytest.fixture(autouse=True)
def micro_latent(monkeypatch):
    monkeypatch.setitem(PRESETS, MICRO_LATENT.name, MICRO_LATENT)
    return MICRO_LATENT


def _autoencoder(folder: Path, seed: int = 0, data: Path | None = None) -> Path:
    """A random ae-test autoencoder; with ``data``, its latents normalised on that dataset's frames."""
    torch.manual_seed(seed)
    model = RGBDNAutoencoder(get_autoencoder_preset("ae-test")).eval()
    if data is not None:
        from tesseract4d.model.autoencoder_trainer import FrameSet, measure_latent_stats

        frames = FrameSet.load(data, height=32, width=32, model_space=model.model_space)
        model.set_latent_stats(*measure_latent_stats(model, frames.frames))
    return save_autoencoder(model, folder)


def _config(data, out, ae, **kw):
    from tesseract4d.model.trainer import TrainConfig

    base = dict(data=data, out=out, preset=MICRO_LATENT.name, autoencoder=ae, max_steps=2, val_every=0,
                ckpt_every=0, quiet=True)
    base.update(kw)
    return TrainConfig(**base)


def test_latent_preset_shapes():
    """latent-128: 128² x 16 frames -> 16 x (16x16 latents) -> 2x2 patches, temporal patch 1 = 1,024 tokens."""
    from tesseract4d.model.codec import AutoencoderCodec
    from tesseract4d.model.build import build_transformer

    preset = get_preset("latent-128")
    assert (preset.height, preset.width, preset.num_frames) == (128, 128, 16)
    assert preset.backbone["patch_size_t"] == 1
    ae_cfg = get_autoencoder_preset("ae-f8c32")
    assert ae_cfg.spatial_compression == 8 and ae_cfg.latent_shape == (32, 16, 16)
    tokens = preset.num_frames * (ae_cfg.latent_shape[1] // preset.backbone["patch_size"]) ** 2
    assert 1000 <= tokens <= 2000
    torch.manual_seed(0)
    codec = AutoencoderCodec(RGBDNAutoencoder(ae_cfg))
    model = build_transformer(preset, codec)
    assert model.config.modality_channels == {"latent": 32}
    x = torch.randn(1, 16, 32, 16, 16)
    with torch.no_grad():
        out = model(x, x[:, :1].expand_as(x), torch.zeros(1, 32, 384), torch.tensor([0.5]))
    assert tuple(out.shape) == (1, 16, 32, 16, 16)
    pixels = torch.rand(1, 2, 7, 128, 128) * 2 - 1
    z = codec.encode(pixels)
    assert tuple(z.shape) == (1, 2, 32, 16, 16)
    assert tuple(codec.decode(z).shape) == (1, 2, 7, 128, 128)


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(10 * torch.log10(4.0 / ((a - b) ** 2).mean()))  # values in [-1, 1]


@pytest.mark.slow
def test_micro_latent_model_overfits_one_clip(tmp_path):
    from tesseract4d.model.pipeline import RGBDNPipeline, make_scheduler
    from tesseract4d.model.trainer import Trainer

    data = write_segmented_dataset(tmp_path / "data", episodes=1)
    ae = _autoencoder(tmp_path / "ae", data=data)
    trainer = Trainer(_config(data, tmp_path / "run", ae, max_steps=300, batch_size=4))
    losses = [trainer.train_step()["loss"] for _ in range(300)]
    assert sum(losses[-10:]) / 10 < 0.2 * losses[0]
    latents, text = trainer.data.clip(0)  # (T, C, h, w), encoded from the dataset's pixels
    target = trainer.codec.decode(latents[None]).cpu()  # (1, T, 7, H, W): what the autoencoder can show
    ep = df.read_episode(df.list_episode_files(data)[0])
    cam = ep.cameras["close"]
    first = trainer.model_space.encode(cam.rgb[:1], cam.depth_m[:1], cam.normal_cam[:1])  # (1, 7, H, W) pixels
    pipe = RGBDNPipeline(trainer.ema.model, make_scheduler(), trainer.codec, trainer.text_encoder, trainer.preset,
                         trainer.model_space)
    pred = pipe(first, [text], num_inference_steps=4, generator=torch.Generator().manual_seed(0))
    static = target[:, :1].expand_as(target)
    psnr, psnr_static = _psnr(pred[:, 1:], target[:, 1:]), _psnr(static[:, 1:], target[:, 1:])
    print(f"micro latent model: PSNR {psnr:.1f} dB, static world {psnr_static:.1f} dB")
    assert psnr > 20.0 and psnr > psnr_static + 4.0, (psnr, psnr_static)  # measured: 22.0 vs 16.6


def test_checkpoint_save_load_identical_samples_and_autoencoder_checks(tmp_path):
    from tesseract4d.model.latent_cache import default_cache_dir
    from tesseract4d.model.predict import load_pipeline
    from tesseract4d.model.trainer import Trainer

    data = write_segmented_dataset(tmp_path / "data", episodes=2)
    ae = _autoencoder(tmp_path / "ae")
    final = Trainer(_config(data, tmp_path / "run", ae, condition_noise=0.1, moving_weight=2.0, object_weight=2.0,
                            scene_object_weight=4.0)).train()
    cfg = json.loads((final / "tesseract4d_config.json").read_text())
    assert cfg["recipe"]["object_weight"] == 2.0 and cfg["recipe"]["scene_object_weight"] == 4.0
    assert len(cfg["autoencoder"]["hash"]) == 16
    assert (default_cache_dir(data, "close") / "cache.json").is_file()
    first = torch.rand(1, 7, 32, 32) * 2 - 1
    samples = []
    for _ in range(2):
        pipe = load_pipeline(final)
        samples.append(pipe(first, ["push the square to the right"], generator=torch.Generator().manual_seed(3)))
    assert tuple(samples[0].shape) == (1, 8, 7, 32, 32)
    assert torch.equal(samples[0], samples[1])
    # the autoencoder missing, or another one in its place: one-line errors that say what to run
    broken = tmp_path / "broken"
    shutil.copytree(final, broken)
    shutil.rmtree(broken / "autoencoder")
    with pytest.raises(UserError, match="checkpoint export"):
        load_pipeline(broken)
    _autoencoder(broken / "autoencoder", seed=5)
    with pytest.raises(UserError, match="re-export"):
        load_pipeline(broken)


def test_half_export_is_half_the_size_and_samples_like_the_float32_export(tmp_path):
    from safetensors import safe_open

    from tesseract4d import cli
    from tesseract4d.model.predict import load_pipeline
    from tesseract4d.model.trainer import Trainer

    data = write_segmented_dataset(tmp_path / "data", episodes=2)
    ae = _autoencoder(tmp_path / "ae", data=data)
    run = tmp_path / "run"
    full = Trainer(_config(data, run, ae, max_steps=4)).train()
    assert cli.main(["checkpoint", "export", str(run), "--to", str(tmp_path / "half"), "--half"]) == 0
    half = tmp_path / "half"
    for rel in ("transformer/diffusion_pytorch_model.safetensors", "autoencoder/model.safetensors"):
        with safe_open(str(half / rel), "pt") as f:
            assert {f.get_tensor(k).dtype for k in f.keys()} == {torch.float16}, rel
        assert (half / rel).stat().st_size < 0.6 * (full / rel).stat().st_size, rel
    cfg = json.loads((half / "tesseract4d_config.json").read_text())
    assert cfg["weights_dtype"] == "float16"
    assert cfg["autoencoder"]["trained_with_hash"] == json.loads((full / "tesseract4d_config.json").read_text())["autoencoder"]["hash"]
    first = torch.rand(1, 7, 32, 32) * 2 - 1
    # fp32 compute on every CPU, so the comparison measures the weights' precision alone
    a, b = (load_pipeline(c, precision="fp32")(first, ["push the square to the right"],
                                               generator=torch.Generator().manual_seed(3)) for c in (full, half))
    assert a.dtype == b.dtype == torch.float32
    diff = (a - b).abs().flatten()  # model space is [-1, 1]; a few pixels at the no-depth cut-off or
    # a near-zero normal may flip, so bound the mean and the 99th percentile
    assert diff.mean() < 0.01 and diff.quantile(0.99) < 0.05, (float(diff.mean()), float(diff.quantile(0.99)))
    assert cli.main(["train", "--half", "--out", str(tmp_path / "x"), "--data", str(data)]) == 2


def test_time_logit_normal_draws_most_times_at_middle_noise():
    """--time-logit-normal m: t = sigmoid(m n), n ~ N(0, 1), drawn from the generator's normal stream
    (the uniform draw is untouched at 0): symmetric about t = 0.5, about 68 % of the draws between
    sigmoid(-m) and sigmoid(m) (0.27-0.73 at m = 1; uniform: 46 %); at 0 the draw is torch.rand's."""
    from tesseract4d.model.recipe import sample_times

    n = 20000
    z = torch.randn(n, generator=torch.Generator().manual_seed(7))
    t = sample_times(n, torch.Generator().manual_seed(7), logit_normal=1.0)
    assert torch.allclose(t, torch.sigmoid(z))
    assert float(t.min()) > 0.0 and float(t.max()) < 1.0
    assert abs(float(t.median()) - 0.5) < 0.02
    inner = float(((t > torch.sigmoid(torch.tensor(-1.0))) & (t < torch.sigmoid(torch.tensor(1.0)))).float().mean())
    assert abs(inner - 0.6827) < 0.02
    assert torch.equal(sample_times(n, torch.Generator().manual_seed(7), logit_normal=0.0),
                       torch.rand(n, generator=torch.Generator().manual_seed(7)))


def test_time_logit_normal_trains_and_is_recorded(tmp_path):
    from tesseract4d.model.predict import load_pipeline
    from tesseract4d.model.trainer import Trainer

    data = write_segmented_dataset(tmp_path / "data", episodes=1)
    final = Trainer(_config(data, tmp_path / "run", _autoencoder(tmp_path / "ae"), time_logit_normal=1.0)).train()
    recipe = load_pipeline(final).config["recipe"]
    assert recipe["time_logit_normal"] == 1.0
    for bad in (-1.0, float("nan")):
        with pytest.raises(UserError, match="--time-logit-normal"):
            Trainer(_config(data, tmp_path / "run2", _autoencoder(tmp_path / "ae"), time_logit_normal=bad))
    assert not (tmp_path / "run2").exists()


def test_rephrase_trains_on_other_wordings_and_is_recorded(tmp_path, monkeypatch):
    """``--rephrase``: the text encoder sees the paraphrases the trainer was given; the lever travels with
    the checkpoint; a trainer asked to rephrase without paraphrases refuses."""
    from tesseract4d.model.predict import load_pipeline
    from tesseract4d.model.trainer import Trainer

    data = write_segmented_dataset(tmp_path / "data", episodes=2)
    words = {"push the square to the right": ["push the square to the right", "slide the square right"]}
    cfg = _config(data, tmp_path / "run", _autoencoder(tmp_path / "ae"), batch_size=4, rephrase=1.0)
    with pytest.raises(ValueError, match="paraphrases"):
        Trainer(cfg)
    trainer = Trainer(cfg, lambda text: words.get(text, [text]))
    encoded = []
    original = trainer.text_encoder.encode
    monkeypatch.setattr(trainer.text_encoder, "encode", lambda texts: encoded.extend(texts) or original(texts))
    for step in range(4):
        trainer.compute_loss(step)
    # Only the rightward episode has paraphrases: its two wordings and the leftward one, nothing else.
    assert set(encoded) == {"push the square to the right", "slide the square right", "push the square to the left"}
    final = trainer.train()
    assert load_pipeline(final).config["recipe"]["rephrase"] == 1.0


def test_group_batches_share_noise_and_time_per_scene_and_are_recorded(tmp_path, monkeypatch):
    """``--group-batches``: the trainer's batches are whole counterfactual groups with one noise and one
    diffusion time per group; the swap shows siblings' noisy samples; the recipe travels with the
    checkpoint. A dataset without groups, or the group levers without group batches, is refused."""
    from tesseract4d.testing.synthetic_scene import write_grouped_dataset

    from tesseract4d.model.predict import load_pipeline
    from tesseract4d.model.trainer import Trainer

    data = write_grouped_dataset(tmp_path / "data", scenes=2, singles=1)
    ae = _autoencoder(tmp_path / "ae")
    trainer = Trainer(_config(data, tmp_path / "run", ae, batch_size=4, group_batches=True, counterfactual_swap=1.0))
    seen = []
    original = trainer.denoising_loss

    def record(x0, first, text, t, noise, objects=None, *, shown=None, history=None):
        assert history is None  # a one-frame preset draws no history
        seen.append((x0, t, noise, shown))
        return original(x0, first, text, t, noise, objects, shown=shown, history=history)

    groups = []
    sample_group_batch = trainer.data.sample_group_batch
    monkeypatch.setattr(trainer.data, "sample_group_batch",
                        lambda *a, **k: (lambda out: groups.append(out[-1]) or out)(sample_group_batch(*a, **k)))
    monkeypatch.setattr(trainer, "denoising_loss", record)
    for step in range(6):
        trainer.compute_loss(step)
    for (x0, t, noise, shown), leaders in zip(seen, groups, strict=True):
        for k, leader in enumerate(leaders):
            assert torch.equal(noise[k], noise[leader]) and t[k] == t[leader]
            assert torch.equal(x0[k, 0], x0[leader, 0])  # one scene: the same first frame
            j = shown[k]
            assert leaders[j] == leader  # shown its own or a sibling's noisy sample
    # Over a few steps some clip was shown a sibling (swap probability 1 at times >= SWAP_MIN_T).
    assert any(j != k for *_, shown in seen for k, j in enumerate(shown))
    final = trainer.train()
    recipe = load_pipeline(final).config["recipe"]
    assert recipe["group_batches"] is True and recipe["counterfactual_swap"] == 1.0

    with pytest.raises(UserError, match="--group-batches"):
        Trainer(_config(data, tmp_path / "run2", ae, counterfactual_swap=0.5))
    with pytest.raises(UserError, match="--counterfactual-swap"):
        Trainer(_config(data, tmp_path / "run3", ae, group_batches=True, counterfactual_swap=1.5))
    plain = write_segmented_dataset(tmp_path / "plain", episodes=2)
    with pytest.raises(UserError, match="--instructions-per-scene"):
        Trainer(_config(plain, tmp_path / "run4", ae, group_batches=True))
    assert not (tmp_path / "run4").exists()  # refused while setting up: nothing left behind


def test_bad_inputs_are_user_errors(tmp_path):
    from tesseract4d.model.trainer import Trainer

    ae = _autoencoder(tmp_path / "ae")
    wrong = write_segmented_dataset(tmp_path / "data16", episodes=1, size=64)
    with pytest.raises(UserError, match="--resolution 32"):
        Trainer(_config(wrong, tmp_path / "run1", ae))
    data = write_segmented_dataset(tmp_path / "data", episodes=1)
    with pytest.raises(UserError, match="--autoencoder"):
        Trainer(_config(data, tmp_path / "run2", None))
    for weight in (0.0, float("inf")):
        with pytest.raises(UserError, match="--scene-object-weight"):
            Trainer(_config(data, tmp_path / "run5", ae, scene_object_weight=weight))
    assert not any((tmp_path / f"run{k}").exists() for k in range(1, 6))


def test_init_fine_tunes_a_checkpoint_in_its_own_latent_space(tmp_path):
    """`train --init CKPT`: the new run starts from the checkpoint's transformer weights (float16 ones
    too) with its own schedule, uses the autoencoder inside the checkpoint, names what it started from,
    and refuses another preset, a velocity target, or an autoencoder with other latents."""
    from safetensors.torch import load_file

    from tesseract4d import cli
    from tesseract4d.model.checkpoint import weights_digest
    from tesseract4d.model.trainer import Trainer

    data = write_segmented_dataset(tmp_path / "data", episodes=1)
    ae = _autoencoder(tmp_path / "ae", data=data)
    Trainer(_config(data, tmp_path / "first", ae, max_steps=3)).train()
    assert cli.main(["checkpoint", "export", str(tmp_path / "first"), "--to", str(tmp_path / "ckpt"), "--half"]) == 0
    ckpt = tmp_path / "ckpt"
    start = load_file(str(ckpt / "transformer" / "diffusion_pytorch_model.safetensors"))

    trainer = Trainer(_config(data, tmp_path / "more", None, init=ckpt, max_steps=2))
    assert trainer.cfg.autoencoder == ckpt / "autoencoder"  # the checkpoint's own, hash-checked
    for name, value in trainer.ema.model.state_dict().items():
        assert torch.equal(value.cpu(), start[name].float()), name
    assert trainer.step == 0 and trainer.optimizer.state_dict()["state"] == {}
    final = trainer.train()
    training = json.loads((final / "tesseract4d_config.json").read_text())["training"]
    assert training["init"] == str(ckpt) and training["init_digest"] == weights_digest(ckpt)
    after = load_file(str(final / "transformer" / "diffusion_pytorch_model.safetensors"))
    assert any(not torch.equal(after[k], start[k].float()) for k in start)  # it trained from there
    # A resumed run keeps the record of its start: --init must hold the same weights as at the start.
    assert cli.main(["checkpoint", "export", str(tmp_path / "more"), "--to", str(tmp_path / "ckpt2"), "--half"]) == 0
    with pytest.raises(UserError, match="started from .* resume with --init naming those weights"):
        Trainer(_config(data, tmp_path / "more", None, init=tmp_path / "ckpt2", max_steps=3, resume=True))
    with pytest.raises(UserError, match=re.escape(f"started from --init {ckpt}; resume it with --init {ckpt} --resume")):
        Trainer(_config(data, tmp_path / "more", None, max_steps=3, resume=True))
    assert Trainer(_config(data, tmp_path / "more", None, init=ckpt, max_steps=3, resume=True)).step == 2
    # ... and the autoencoder it trained in: another one's latents are another space.
    other = _autoencoder(tmp_path / "ae_other", seed=5, data=data)
    with pytest.raises(UserError, match=r"was trained in the latents of autoencoder .* resume with --autoencoder "):
        Trainer(_config(data, tmp_path / "first", other, max_steps=4, resume=True))
    assert Trainer(_config(data, tmp_path / "first", ae, max_steps=4, resume=True)).step == 3

    velocity = shutil.copytree(ckpt, tmp_path / "velocity")  # as written before the velocity target was removed
    config = json.loads((velocity / "tesseract4d_config.json").read_text())
    config["recipe"]["prediction"] = "velocity"
    (velocity / "tesseract4d_config.json").write_text(json.dumps(config))
    with pytest.raises(UserError, match="predicts 'velocity'"):
        Trainer(_config(data, tmp_path / "r1", None, init=velocity))
    with pytest.raises(UserError, match="makes other latents"):
        Trainer(_config(data, tmp_path / "r2", _autoencoder(tmp_path / "other", seed=7), init=ckpt))
    with pytest.raises(UserError, match="--preset micro-latent"):
        Trainer(_config(data, tmp_path / "r3", None, init=ckpt, preset="latent-128"))
    with pytest.raises(UserError, match="the input"):
        Trainer(_config(data, ckpt / "inside", None, init=ckpt))
    assert not (tmp_path / "r1").exists() and not (ckpt / "inside").exists()


@pytest.mark.slow
def test_a_latent_teacher_distils_into_a_few_step_student_that_carries_its_autoencoder(tmp_path):
    """`distill` of a latent checkpoint: the student trains in the teacher's latent space with the
    autoencoder copied inside the teacher (hash-checked), sees clean first
    frames, exports with that autoencoder, and follows the guided multi-step teacher in 2 unguided steps
    more closely than the teacher's own 2 steps."""
    from tesseract4d import cli
    from tesseract4d.model.predict import load_pipeline
    from tesseract4d.model.reflow import PairsConfig, ReflowPairs, generate_pairs, model_space_psnr
    from tesseract4d.model.trainer import Trainer

    data = write_segmented_dataset(tmp_path / "data", episodes=2)
    ae = _autoencoder(tmp_path / "ae", data=data)
    teacher = Trainer(_config(data, tmp_path / "teacher", ae, max_steps=60, condition_noise=0.1)).train()
    pairs = generate_pairs(PairsConfig(teacher=teacher, data=data, out=tmp_path / "pairs", num_pairs=16, shard_size=8,
                                       batch_size=8, teacher_steps=8, text_guidance=2.0), progress=False)
    run = tmp_path / "student"
    assert cli.main(["distill", "--teacher", str(teacher), "--pairs", str(pairs), "--out", str(run), "--student-steps",
                     "2", "--max-steps", "120", "--batch-size", "4", "--lr", "1e-3", "--val-every", "0",
                     "--ckpt-every", "0", "--quiet"]) == 0
    student = load_pipeline(run / "final")
    teacher_cfg = json.loads((teacher / "tesseract4d_config.json").read_text())
    assert student.config["autoencoder"]["hash"] == teacher_cfg["autoencoder"]["hash"]
    assert student.config["recipe"]["condition_noise"] == 0.0
    assert (student.preset.num_steps, student.preset.text_guidance) == (2, 1.0)

    teacher_pipe, p = load_pipeline(teacher), ReflowPairs(pairs)
    first, texts = p.first[:8].float(), p.instructions[:8]
    noise = torch.randn(teacher_pipe.latent_shape(8), generator=torch.Generator().manual_seed(123))  # new noise
    target = teacher_pipe(first, texts, num_inference_steps=8, text_guidance=2.0, latents=noise, output_type="latent")
    few = teacher_pipe(first, texts, num_inference_steps=2, text_guidance=2.0, latents=noise, output_type="latent")
    distilled = student(first, texts, latents=noise, output_type="latent")
    psnr_student = model_space_psnr(student.codec, distilled, target)
    psnr_few = model_space_psnr(student.codec, few, target)
    print(f"student 2 steps {psnr_student:.2f} dB, teacher 2 steps {psnr_few:.2f} dB (vs teacher 8 guided steps)")
    assert psnr_student > psnr_few + 1.0, (psnr_student, psnr_few)


def test_decoder_only_fine_tune_swaps_into_the_checkpoint_with_the_same_latents(tmp_path):
    """train-autoencoder with decoder_only keeps the encoder and latent statistics bit for bit, and
    checkpoint swap-decoder puts the new decoder into a copy of the checkpoint: same latents, new pixels; an
    autoencoder that encodes differently, or --decoder-only without --init, is refused."""
    from tesseract4d import cli
    from tesseract4d.model.autoencoder_loading import load_autoencoder
    from tesseract4d.model.predict import load_pipeline
    from tesseract4d.model.trainer import Trainer

    data = write_segmented_dataset(tmp_path / "data", episodes=2)
    final = Trainer(_config(data, tmp_path / "run", _autoencoder(tmp_path / "ae", data=data))).train()
    dec = tmp_path / "dec"
    assert cli.main(["train-autoencoder", "--init", str(final / "autoencoder"), "--decoder-only", "--data", str(data),
                     "--out", str(dec), "--preset", "ae-test", "--max-steps", "3", "--batch-size", "2",
                     "--lr", "1e-2", "--warmup-steps", "1", "--set", "precision=fp32", "--quiet"]) == 0
    old, new = load_autoencoder(final / "autoencoder"), load_autoencoder(dec / "autoencoder")
    assert new.config.latent_mean == old.config.latent_mean and new.config.latent_std == old.config.latent_std
    so, sn = old.state_dict(), new.state_dict()
    encoder_keys = [k for k in so if k.startswith(("vae.encoder.", "vae.quant_conv."))]
    assert encoder_keys and all(torch.equal(so[k], sn[k]) for k in encoder_keys)
    assert not all(torch.equal(so[k], sn[k]) for k in so if k.startswith("vae.decoder."))

    swapped = tmp_path / "swapped"
    assert cli.main(["checkpoint", "swap-decoder", "--checkpoint", str(final), "--autoencoder", str(dec / "autoencoder"),
                     "--to", str(swapped), "--half"]) == 0
    cfg = json.loads((swapped / "tesseract4d_config.json").read_text())
    before = json.loads((final / "tesseract4d_config.json").read_text())["autoencoder"]["hash"]
    assert cfg["autoencoder"]["trained_with_hash"] == before == cfg["autoencoder"]["decoder_replaced"]["previous_hash"]
    first = torch.rand(1, 7, 32, 32) * 2 - 1
    a, b = load_pipeline(final, precision="fp32"), load_pipeline(swapped, precision="fp32")
    za = a(first, ["push"], num_inference_steps=2, generator=torch.Generator().manual_seed(1), output_type="latent")
    zb = b(first, ["push"], num_inference_steps=2, generator=torch.Generator().manual_seed(1), output_type="latent")
    assert torch.equal(za, zb)
    assert not torch.equal(a.codec.decode(za), b.codec.decode(zb))
    # A swap and an export own their folders apart: neither replaces the other's without --overwrite.
    assert cli.main(["checkpoint", "export", str(tmp_path / "run"), "--to", str(swapped)]) == 2
    assert cfg == json.loads((swapped / "tesseract4d_config.json").read_text())
    exported = tmp_path / "exported"
    assert cli.main(["checkpoint", "export", str(tmp_path / "run"), "--to", str(exported)]) == 0
    assert cli.main(["checkpoint", "swap-decoder", "--checkpoint", str(final), "--autoencoder", str(dec / "autoencoder"),
                     "--to", str(exported)]) == 2
    assert cli.main(["checkpoint", "swap-decoder", "--checkpoint", str(final), "--autoencoder", str(dec / "autoencoder"),
                     "--to", str(swapped), "--half"]) == 0  # its own earlier swap: replaced

    other = _autoencoder(tmp_path / "other", seed=9, data=data)
    with pytest.raises(UserError, match="ae-f8c32-decoder"):
        from tesseract4d.model.checkpoint_copies import replace_decoder

        replace_decoder(final, other, tmp_path / "refused")
    assert not (tmp_path / "refused").exists()
    from tesseract4d.model.autoencoder_trainer import AutoencoderTrainConfig, AutoencoderTrainer

    with pytest.raises(UserError, match="--init"):
        AutoencoderTrainer(AutoencoderTrainConfig(data=data, out=tmp_path / "noinit", preset="ae-test",
                                                  decoder_only=True, quiet=True))


@pytest.mark.parametrize("damage", ["junk", "truncated"])
def test_swap_decoder_names_a_corrupt_autoencoder(tmp_path, capsys, damage):
    """An --autoencoder whose config is fine but whose weights are not a safetensors file (or are cut
    short) is one error line naming the file, as `predict` names a corrupt checkpoint; nothing is written
    (before: a SafetensorError traceback)."""
    from tesseract4d import cli
    from tesseract4d.model.trainer import Trainer

    data = write_segmented_dataset(tmp_path / "data", episodes=1)
    final = Trainer(_config(data, tmp_path / "run", _autoencoder(tmp_path / "ae", data=data))).train()
    bad = shutil.copytree(final / "autoencoder", tmp_path / "bad")
    weights = bad / "model.safetensors"
    weights.write_bytes(b"junk" if damage == "junk" else weights.read_bytes()[:-100])
    rc = cli.main(["checkpoint", "swap-decoder", "--checkpoint", str(final), "--autoencoder", str(bad),
                   "--to", str(tmp_path / "to")])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err
    assert f"tesseract4d checkpoint swap-decoder: error: autoencoder weights {weights} are corrupt or truncated (" in err, err
    assert "train them again with `tesseract4d train-autoencoder`" in err
    assert not (tmp_path / "to").exists()
    # encode-latents reads the same weights the same way (before: the same traceback).
    rc = cli.main(["encode-latents", "--data", str(data), "--autoencoder", str(bad), "--cache", str(tmp_path / "cache")])
    assert rc == 2 and f"autoencoder weights {weights} are corrupt or truncated" in capsys.readouterr().err
    assert not (tmp_path / "cache").exists()


def test_heldout_evaluation_scores_the_autoencoder_ceiling_once_per_autoencoder(tmp_path):
    """A latent checkpoint at the data's resolution gets a ceiling row: the truth encoded and decoded
    by its autoencoder; two checkpoints sharing one autoencoder get one row."""
    from tesseract4d.evaluation.heldout import HeldoutConfig, autoencoder_round_trip, evaluate_heldout
    from tesseract4d.model.predict import load_pipeline
    from tesseract4d.model.trainer import Trainer

    data = write_segmented_dataset(tmp_path / "data", episodes=2)
    final = Trainer(_config(data, tmp_path / "run", _autoencoder(tmp_path / "ae", data=data))).train()
    twin = tmp_path / "twin"
    shutil.copytree(final, twin)
    report = evaluate_heldout(HeldoutConfig(checkpoint=[final, twin], data=data, num_steps=2, precision="fp32"),
                              progress=False)
    assert list(report["methods"]) == ["final", "final_raw", "twin", "twin_raw", "final_autoencoder", "static"]
    assert "ceiling" in report["methods"]["final_autoencoder"]
    ceiling = report["summary"]["final_autoencoder"]
    assert all(np.isfinite(ceiling[k]) for k in ("rgb_psnr_db", "depth_abs_rel", "normal_mean_deg", "chamfer_l1_m"))
    # The round trip is the codec's own: encoding and decoding the truth by hand gives the same frames.
    pipe = load_pipeline(final, precision="fp32")
    gt = df.read_episode(df.list_episode_files(data)[0])
    trip = autoencoder_round_trip(pipe, gt, "close").cameras["close"]
    cam = gt.cameras["close"]
    x = pipe.model_space.encode(cam.rgb, cam.depth_m, cam.normal_cam)[None]
    rgb, _, _ = pipe.model_space.decode(pipe.codec.decode(pipe.codec.encode(x))[0])
    assert np.array_equal(trip.rgb, rgb) and trip.rgb.shape == cam.rgb.shape


def test_text_noise_is_relative_keeps_padding_and_is_recorded(tmp_path):
    """``--text-noise``: noise of at most S times each token's size, none on padding, nothing drawn at 0; the
    lever travels with the checkpoint, and a negative or NaN value is refused before anything is written."""
    from tesseract4d.model.predict import load_pipeline
    from tesseract4d.model.recipe import augment_text
    from tesseract4d.model.trainer import Trainer

    text = torch.zeros(64, 6, 32)
    text[:, :4] = torch.randn(64, 4, 32) * torch.tensor([0.5, 2.0, 8.0, 1.0])[None, :, None]  # 2 padding tokens
    g = torch.Generator().manual_seed(0)
    assert augment_text(text, 0.0, g) is text and torch.equal(torch.rand(1, generator=g),
                                                              torch.rand(1, generator=torch.Generator().manual_seed(0)))
    out = augment_text(text, 0.5, torch.Generator().manual_seed(1))
    assert torch.equal(out[:, 4:], text[:, 4:])  # padding stays zero
    rms = text[:, :4].pow(2).mean(-1).sqrt()
    rel = (out[:, :4] - text[:, :4]).pow(2).mean(-1).sqrt() / rms  # (64, 4): one relative std per clip
    assert float(rel.max()) < 0.5 * 1.6 and float(rel.mean()) > 0.25 * 0.6  # std U(0, 0.5), estimated from 32 values
    assert float((rel.std(1) / rel.mean(1)).median()) < 0.35  # the same relative size on a small and a large token

    data = write_segmented_dataset(tmp_path / "data", episodes=1)
    final = Trainer(_config(data, tmp_path / "run", _autoencoder(tmp_path / "ae"), text_noise=0.3)).train()
    assert load_pipeline(final).config["recipe"]["text_noise"] == 0.3
    for bad in (-0.1, float("nan")):
        with pytest.raises(UserError, match="--text-noise"):
            Trainer(_config(data, tmp_path / "run2", _autoencoder(tmp_path / "ae"), text_noise=bad))
    assert not (tmp_path / "run2").exists()
