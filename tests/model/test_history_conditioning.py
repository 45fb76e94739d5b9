"""History conditioning: a clip after a rollout's first continues from the last k frames so far.

The k given frames fill the condition's first k latent frames (the rest repeat the last of them), the
network's frames are corrections of them, a rollout adds ``num_frames - k`` new frames per clip, and
k = 1 is the rollout of one frame per clip. Training gives a share of the clips their first k true
frames, noised, as history and charges the loss on the later frames only.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch
from tesseract4d.testing.model_fixtures import MICRO

from tesseract4d.errors import UserError
from tesseract4d.instruction_schedule import clip_new_frames
from tesseract4d.model.codec import PixelCodec, make_condition
from tesseract4d.model.model_space import MODALITY_CHANNELS, NUM_CHANNELS, ModelSpace
from tesseract4d.model.pipeline import RGBDNPipeline, make_scheduler
from tesseract4d.model.presets import CONDITION_FIRST, CONDITION_REPEAT
from tesseract4d.model.recipe import draw_history, history_loss_mask
from tesseract4d.model.rgbdn_transformer import RGBDNTransformer

K = 3  # history frames of the micro clips of 8 frames


@pytest.fixture(scope="module")
def text_encoder():
    from tesseract4d.model.build import build_text_encoder

    return build_text_encoder(MICRO)


def _pipe(text_encoder, history_frames: int) -> RGBDNPipeline:
    """The micro preset with a random-init network (its output heads are not zero, so every input counts)."""
    preset = dataclasses.replace(MICRO, history_frames=history_frames)
    torch.manual_seed(0)
    net = RGBDNTransformer(dict(preset.backbone), dict(MODALITY_CHANNELS)).eval()
    return RGBDNPipeline(net, make_scheduler(), PixelCodec(), text_encoder, preset, ModelSpace())


def _first(seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand((1, NUM_CHANNELS, MICRO.height, MICRO.width), generator=g) * 2 - 1  # (1, 7, H, W)


def _conditions_seen(pipe):
    """(condition, history_frames) of every transformer call, recorded by a forward pre-hook."""
    seen: list[tuple[torch.Tensor, int]] = []
    handle = pipe.transformer.register_forward_pre_hook(
        lambda module, args, kwargs: seen.append((args[1].clone(), kwargs.get("history_frames", 1))), with_kwargs=True)
    return seen, handle


def test_the_condition_holds_the_given_frames_first():
    given = torch.randn(2, K, 4, 3, 3)  # (b, k, c, h, w)
    rep = make_condition(given, 8, CONDITION_REPEAT)
    assert rep.shape == (2, 8, 4, 3, 3)
    assert torch.equal(rep[:, :K], given) and torch.equal(rep[:, K:], given[:, -1:].expand(-1, 8 - K, -1, -1, -1))
    first = make_condition(given, 8, CONDITION_FIRST)
    assert torch.equal(first[:, :K], given) and not first[:, K:].any()
    # One given frame: the first frame repeated (or followed by zeros), as before history existed.
    one = given[:, :1]
    assert torch.equal(make_condition(one, 8, CONDITION_REPEAT), one.expand(-1, 8, -1, -1, -1))
    with pytest.raises(ValueError, match="do not fit"):
        make_condition(torch.randn(1, 9, 4, 3, 3), 8, CONDITION_REPEAT)


def test_each_output_frame_corrects_its_given_frame():
    """x0_hat = base + correction: frames < k on their own given frame, later ones on the last (k = 1: the
    first frame for all, bit for bit as the one-frame forward)."""
    torch.manual_seed(0)
    net = RGBDNTransformer(dict(MICRO.backbone), dict(MODALITY_CHANNELS)).eval()
    x = torch.randn(1, MICRO.num_frames, NUM_CHANNELS, MICRO.height, MICRO.width)
    text = torch.randn(1, MICRO.max_text_tokens, 384)
    t = torch.tensor([0.7])
    given = torch.randn(1, K, NUM_CHANNELS, MICRO.height, MICRO.width)
    cond = make_condition(given, MICRO.num_frames, MICRO.condition)
    with torch.no_grad():
        plain = net(x, cond, text, t)  # the same network, every frame on given frame 0
        with_history = net(x, cond, text, t, history_frames=K)
        one = make_condition(given[:, :1], MICRO.num_frames, MICRO.condition)
        assert torch.equal(net(x, one, text, t), net(x, one, text, t, history_frames=1))
    base = torch.cat([given, given[:, -1:].expand(-1, MICRO.num_frames - K, -1, -1, -1)], dim=1)
    torch.testing.assert_close(with_history - base, plain - given[:, :1], atol=1e-5, rtol=0)


def test_a_clip_changes_when_its_older_history_frames_change(text_encoder):
    """Fails when the history is ignored: same noise, same last given frame, only frames 0 .. k-2 of the
    history differ, and the clip's new frames differ."""
    pipe = _pipe(text_encoder, K)
    text = text_encoder.encode(["push the square to the left"])
    history = torch.stack([_first(s)[0] for s in range(K)])[None]  # (1, k, 7, H, W)
    changed = history.clone()
    changed[:, :K - 1] = torch.stack([_first(10 + s)[0] for s in range(K - 1)])[None]
    noise = torch.randn(pipe.latent_shape(1), generator=torch.Generator().manual_seed(1))

    def clip(h):
        return pipe._denoise_clip(h[:, 0], text, torch.zeros_like(text), 2, 1.0, 1.0, torch.Generator(), None, 0, 2,
                                  latents=noise, history=h)

    a, b = clip(history), clip(changed)
    assert (a[:, K:] - b[:, K:]).abs().max() > 1e-3
    # The last given frame alone (k = 1 conditioning, as a model without history sees it) gives the same
    # clip for both: the difference above comes from the older frames.
    assert torch.equal(clip(history[:, -1:]), clip(changed[:, -1:]))


def test_the_rollout_continues_from_the_last_k_frames(text_encoder):
    pipe = _pipe(text_encoder, K)
    num_frames = 8 + (8 - K) + 2  # clip 0: frames 0-7; clip 1 adds 8-12; clip 2 adds 13-14
    assert [list(r) for r in clip_new_frames(num_frames, 8, K)] == [list(range(1, 8)), list(range(8, 13)), [13, 14]]
    seen, handle = _conditions_seen(pipe)
    clips: list[torch.Tensor] = []
    try:
        out = pipe(_first(), ["push the square to the left"], num_frames=num_frames, num_inference_steps=2,
                   generator=torch.Generator().manual_seed(0), on_clip=lambda k, f: clips.append(f))
    finally:
        handle.remove()
    assert out.shape == (1, num_frames, NUM_CHANNELS, MICRO.height, MICRO.width)
    assert [c.shape[1] for c in clips] == [8, 5, 2] and torch.equal(torch.cat(clips, dim=1), out)
    assert len(seen) == 3 * 2  # 3 clips x 2 steps
    (cond0, k0), (cond1, k1), (cond2, k2) = seen[0], seen[2], seen[4]
    assert k0 == 1 and torch.equal(cond0, _first()[:, None].expand(-1, 8, -1, -1, -1))
    # Clip 1 continues from frames 5-7 (the codec is the identity), clip 2 from frames 10-12.
    assert k1 == K and torch.equal(cond1[:, :K], out[:, 8 - K:8]) and torch.equal(cond1[:, K:], out[:, 7:8].expand(-1, 8 - K, -1, -1, -1))
    assert k2 == K and torch.equal(cond2[:, :K], out[:, 13 - K:13])


def test_one_history_frame_is_the_rollout_of_one_frame_per_clip(text_encoder):
    """k = 1: each clip continues from the last frame alone, exactly as clip after clip sampled by hand."""
    pipe = _pipe(text_encoder, 1)
    words = ["push the square to the left"]
    rollout = pipe(_first(), words, num_frames=15, num_inference_steps=2, generator=torch.Generator().manual_seed(4))
    g = torch.Generator().manual_seed(4)
    clip0 = pipe(_first(), words, num_inference_steps=2, generator=g)
    clip1 = pipe(clip0[:, -1], words, num_inference_steps=2, generator=g)
    assert torch.equal(rollout, torch.cat([clip0, clip1[:, 1:]], dim=1))


def test_training_history_is_noised_truth_and_its_frames_carry_no_loss():
    x0 = torch.randn(4, 8, 5, 2, 2)  # (b, t, c, h, w)
    g = torch.Generator().manual_seed(0)
    state = g.get_state()
    assert draw_history(x0, 1, 0.5, 0.3, g) is None and draw_history(x0, K, 0.0, 0.3, g) is None
    assert torch.equal(g.get_state(), state)  # nothing drawn: runs without history train as before
    given, chosen = draw_history(x0, K, 1.0, 0.0, g)
    assert chosen.all() and torch.equal(given, x0[:, :K])  # noise level 0: the truth
    given, chosen = draw_history(x0, K, 1.0, 0.5, g)
    assert given.shape == (4, K, 5, 2, 2) and not torch.equal(given, x0[:, :K])
    assert (given - x0[:, :K]).abs().max() < 0.5 * (x0[:, :K].abs().max() + 6)  # (1 - s) x + s noise, s <= 0.5
    chosen = torch.tensor([True, False, True, False])
    weights = history_loss_mask(x0, K, chosen, None)
    assert weights.shape == (4, 8, 1, 2, 2)
    assert not weights[chosen, :K].any() and (weights[chosen, K:] == 1).all() and (weights[~chosen] == 1).all()
    doubled = history_loss_mask(x0, K, chosen, torch.full((4, 8, 1, 2, 2), 2.0))
    assert (doubled[~chosen] == 2).all() and not doubled[chosen, :K].any()


def test_a_history_run_trains_and_its_checkpoint_samples_with_its_k(micro_preset, tmp_path):
    from tesseract4d.testing.synthetic_scene import write_synthetic_dataset

    from tesseract4d.model.predict import load_pipeline
    from tesseract4d.model.trainer import TrainConfig, Trainer

    data = write_synthetic_dataset(tmp_path / "data", episodes=2)
    cfg = TrainConfig(data=data, out=tmp_path / "run", preset=micro_preset.name, max_steps=2, val_every=0, ckpt_every=0,
                      quiet=True, history_frames=K, history_share=1.0, history_noise=0.5)
    final = Trainer(cfg).train()
    pipe = load_pipeline(final, precision="fp32")
    assert pipe.preset.history_frames == K
    assert pipe.config["recipe"]["history_share"] == 1.0 and pipe.config["recipe"]["history_noise"] == 0.5
    assert pipe.config["recipe"]["history_frames"] == K  # `train --recipe-from` the checkpoint trains it again
    with pytest.raises(UserError, match="history_frames=K"):
        Trainer(dataclasses.replace(cfg, out=tmp_path / "run2", history_frames=None))
    with pytest.raises(UserError, match="continues from 1 .. 7"):
        Trainer(dataclasses.replace(cfg, out=tmp_path / "run3", history_frames=8))
