"""Training the first-frame decoder on the latents the default model predicts (model/predicted_latents.py and
the predicted source of model/first_frame_decoder_training.py): the cache holds the checkpoint's own latent
clips per noise seed, the trainer mixes them with the truth's at the configured share, and a predicted clip is
charged only where its latent agrees with the truth's."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tesseract4d.errors import UserError
from tesseract4d.model.first_frame_decoder_training import (
    Clips, FirstFrameTrainConfig, decoder_loss, draw_batch, latent_agreement,
)


def _clips(E=3, T=5, C=8, h=4, factor=4, seeds=2) -> Clips:
    g = torch.Generator().manual_seed(0)
    H = h * factor
    latents = torch.randn(E, T, C, h, h, generator=g)
    predicted = (latents[:, None] + 0.05 * torch.randn(E, seeds, T, C, h, h, generator=g)).half()
    predicted[:, :, :, :, 1, 2] += 3.0  # one cell where every prediction is elsewhere than the truth
    return Clips(frames=torch.zeros(E, T, 7, H, H, dtype=torch.float16), latents=latents,
                 regions=torch.zeros(E, T, 3, H, H, dtype=torch.bool), episode_ids=[f"e{i}" for i in range(E)],
                 objects=torch.zeros(E, T, H, H, dtype=torch.uint8), predicted=predicted)


def test_latent_agreement_marks_the_pixels_of_the_cells_that_agree():
    g = torch.Generator().manual_seed(1)
    z_true = torch.randn(2, 8, 4, 4, generator=g)
    z_pred = z_true + 0.1 * torch.randn(2, 8, 4, 4, generator=g)
    z_pred[0, :, 1, 2] += 2.0
    agree = latent_agreement(z_pred, z_true, tol=0.75, factor=4)
    assert agree.shape == (2, 1, 16, 16)
    assert (agree[0, 0, 4:8, 8:12] == 0).all()
    assert agree.sum() == 2 * 16 * 16 - 16


def test_draw_batch_takes_predicted_latents_at_the_share_and_weights_their_agreement():
    clips = _clips()
    eps, ts = torch.tensor([0, 2]), torch.tensor([[0, 3], [1, 4]])
    cfg = FirstFrameTrainConfig(predicted_share=0.0)
    z, w, predicted = draw_batch(clips, eps, ts, cfg, torch.Generator().manual_seed(0), factor=4)
    assert predicted == [False, False] and (w == 1).all()
    assert torch.equal(z, torch.cat([clips.latents[0, ts[0]], clips.latents[2, ts[1]]]))

    cfg = FirstFrameTrainConfig(predicted_share=1.0, disagree_weight=0.25)
    z, w, predicted = draw_batch(clips, eps, ts, cfg, torch.Generator().manual_seed(0), factor=4)
    assert predicted == [True, True] and z.shape == (4, 8, 4, 4) and w.shape == (4, 1, 16, 16)
    for k, (e, t) in enumerate(zip(eps, ts)):
        assert any(torch.equal(z[2 * k:2 * k + 2], clips.predicted[e, s, t].float()) for s in range(2))
    assert (w[:, :, 4:8, 8:12] == 0.25).all() and w.sum() == 4 * (16 * 16 - 16) + 4 * 16 * 0.25

    cfg = FirstFrameTrainConfig(predicted_share=0.5)
    g = torch.Generator().manual_seed(3)
    share = np.mean([p for _ in range(200) for p in draw_batch(clips, eps, ts, cfg, g, factor=4)[2]])
    assert 0.4 < share < 0.6


def test_a_predicted_clip_is_charged_only_where_it_agrees_with_the_truth():
    """An error (and a lost object) beyond the agreeing cells costs nothing; the same inside them does."""
    cfg = FirstFrameTrainConfig(permanence_loss=1.0)
    target = torch.zeros(1, 7, 16, 16)
    target[:, 4:7] = torch.nn.functional.normalize(torch.ones(1, 3, 16, 16), dim=1)  # unit normals
    objects = torch.zeros(1, 16, 16, dtype=torch.uint8)
    objects[0, 4:8, 8:12] = 1  # a 16-pixel object
    regions = torch.zeros(1, 3, 16, 16, dtype=torch.bool)
    regions[:, 2] = objects.bool()  # it moves
    pred = target.clone()
    pred[:, :3, 4:8, 8:12] = 0.9  # drawn in another colour: lost
    weight = torch.ones(1, 1, 16, 16)
    weight[:, :, 4:8, 8:12] = 0.0  # the prediction's latent is elsewhere there
    loss, parts = decoder_loss(pred, target, regions, cfg, objects, objects.clone(), pixel_weight=weight)
    assert float(loss) == pytest.approx(0.0, abs=1e-6) and parts["lost"] == 0.0
    loss_all, parts_all = decoder_loss(pred, target, regions, cfg, objects, objects.clone(), pixel_weight=torch.ones_like(weight))
    plain, _ = decoder_loss(pred, target, regions, cfg, objects, objects.clone())
    assert parts_all["lost"] > 0.5 and float(loss_all) > 0.5
    assert float(loss_all) == pytest.approx(float(plain), rel=1e-6)


def test_training_mixes_a_predicted_cache_and_refuses_one_of_other_episodes(tmp_path):
    from tesseract4d.model.autoencoder import RGBDNAutoencoder, get_autoencoder_preset, save_autoencoder
    from tesseract4d.model.first_frame_decoder_training import LATENTS_FILE, train
    from tesseract4d.testing.synthetic_scene import write_segmented_dataset

    torch.manual_seed(0)
    save_autoencoder(RGBDNAutoencoder(get_autoencoder_preset("ae-test")).eval(), tmp_path / "base")
    data = write_segmented_dataset(tmp_path / "data", episodes=2, frames=6, size=32)
    cfg = FirstFrameTrainConfig(data=[data], out=tmp_path / "run", init=tmp_path / "base", injection="concat+copy",
                                max_steps=3, warmup_steps=1, frames_per_clip=2, ckpt_every=1, precision="fp32",
                                permanence_loss=1.0, predicted_share=1.0, predicted_latents=tmp_path / "missing.pt")
    with pytest.raises(UserError, match="predicted_latents"):
        train(cfg, log=lambda m: None)
    # A cache in predicted_latents.py's format: the frozen encoder's latents of the same episodes, shifted as a
    # prediction would be in one half of the frame.
    saved = torch.load(tmp_path / "run" / LATENTS_FILE)
    z = saved["latents"][:, None].repeat(1, 2, 1, 1, 1, 1)  # (E, S, T, C, h, w)
    z[..., : z.shape[-1] // 2] += 2.0
    torch.save({"episode_ids": saved["episode_ids"], "latents": z.half()}, tmp_path / "pred.pt")
    torch.save({"episode_ids": ["other/seed_000000"], "latents": z[:1].half()}, tmp_path / "other.pt")
    cfg.predicted_latents = tmp_path / "other.pt"
    with pytest.raises(UserError, match="no predicted latents"):
        train(cfg, log=lambda m: None)
    cfg.predicted_latents = tmp_path / "pred.pt"
    train(cfg, log=lambda m: None)
    history = torch.load(tmp_path / "run" / "state.pt")["history"]
    assert len(history) == 3 and all(h["predicted"] == cfg.clips_per_step for h in history)
    assert np.isfinite([h["loss"] for h in history]).all()


@pytest.mark.slow
def test_the_cache_holds_the_default_models_own_latent_clips_per_noise_seed(tmp_path):
    from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT
    from tesseract4d.model.predict import load_pipeline
    from tesseract4d.model.predicted_latents import load_predicted_latents, main
    from tesseract4d.testing.synthetic_scene import write_segmented_dataset
    from tesseract4d import dataset_format as df

    data = write_segmented_dataset(tmp_path / "data", episodes=2, frames=2, size=128)
    out = tmp_path / "pred.pt"
    assert main(["--checkpoint", str(SHIPPED_CHECKPOINT), "--data", str(data), "--noise-seeds", "0", "1",
                 "--out", str(out)]) == 0
    with pytest.raises(UserError, match="exists"):
        main(["--checkpoint", str(SHIPPED_CHECKPOINT), "--data", str(data), "--out", str(out)])
    cache = torch.load(out)
    assert cache["latents"].shape == (2, 2, 16, 32, 16, 16) and cache["noise_seeds"] == [0, 1]
    assert (cache["latents"][:, 0].float() - cache["latents"][:, 1].float()).abs().mean() > 0.05
    # Seed 1 of episode 1 is the pipeline's latent clip of that episode from seed 1's noise.
    pipe = load_pipeline(SHIPPED_CHECKPOINT)
    ep = df.read_episode(df.list_episode_files(data)[1])
    cam = ep.cameras["close"]
    first = pipe.model_space.encode(cam.rgb[:1], cam.depth_m[:1], cam.normal_cam[:1])
    noise = torch.randn(pipe.latent_shape(1), generator=torch.Generator().manual_seed(1))
    z = pipe(first, [ep.instruction], latents=noise, output_type="latent")
    assert (z[0] - cache["latents"][1, 1].float()).abs().max() < 0.05
    ids = cache["episode_ids"]
    assert torch.equal(load_predicted_latents(out, ids[::-1]), cache["latents"].flip(0))
