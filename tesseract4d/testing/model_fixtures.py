"""Test helpers of the model tests: a micro preset, a tiny random CogVideoX-5B-I2V-shaped model
folder, a short `--max-steps auto` probe on a known clock. Their synthetic RGB-D-N data is in
``synthetic_scene.py``."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from tesseract4d.model.presets import CONDITION_REPEAT, PIXEL, PRESETS, ModelPreset
from tesseract4d.model.text_encoder import minilm_path
from tesseract4d.training.schedule import StepBudget

MICRO = ModelPreset(
    "micro", PIXEL, 32, 32, 8, CONDITION_REPEAT, "minilm", 8,
    backbone=dict(num_attention_heads=2, attention_head_dim=16, num_layers=2, time_embed_dim=32, text_embed_dim=384,
                  max_text_seq_length=8, sample_width=32, sample_height=32, sample_frames=8, patch_size=4,
                  patch_size_t=2, temporal_compression_ratio=1, use_rotary_positional_embeddings=True,
                  use_learned_positional_embeddings=False),
    lr=2e-3, warmup_steps=5, batch_size=2, ema_decay=0.9, text_dropout=0.1, image_dropout=0.05,
    num_steps=4, text_guidance=1.0, image_guidance=1.0,
)

def register_preset(monkeypatch, preset: ModelPreset = MICRO) -> ModelPreset:
    monkeypatch.setitem(PRESETS, preset.name, preset)
    return preset


def micro_latent_preset() -> ModelPreset:
    """The cogvideox-5b preset at a size a test can run (same space, condition, text encoder)."""
    return dataclasses.replace(PRESETS["cogvideox-5b"], name="cogvideox-5b-micro", height=32, width=32, num_frames=9,
                               batch_size=1, warmup_steps=2, num_steps=2, text_guidance=2.0, max_text_tokens=8)


def write_tiny_cogvideox_folder(root: Path) -> Path:
    """A random CogVideoX-5B-I2V-shaped model folder (transformer/, vae/, text_encoder/, tokenizer/)."""
    import torch
    from diffusers import AutoencoderKLCogVideoX, CogVideoXTransformer3DModel
    from transformers import AutoTokenizer, T5Config, T5EncoderModel

    torch.manual_seed(0)
    lc = 4
    vae = AutoencoderKLCogVideoX(
        in_channels=3, out_channels=3, latent_channels=lc,
        down_block_types=("CogVideoXDownBlock3D",) * 3, up_block_types=("CogVideoXUpBlock3D",) * 3,
        block_out_channels=(8, 8, 8), layers_per_block=1, norm_num_groups=2, temporal_compression_ratio=4,
        sample_height=32, sample_width=32,
    )
    vae.save_pretrained(root / "vae")
    # Same structure as CogVideoX-5B-I2V (rotary + learned positions, I2V channels), tiny sizes.
    transformer = CogVideoXTransformer3DModel(
        num_attention_heads=2, attention_head_dim=16, in_channels=2 * lc, out_channels=lc, time_embed_dim=32,
        text_embed_dim=32, num_layers=1, sample_width=8, sample_height=8, sample_frames=9, patch_size=2,
        temporal_compression_ratio=4, max_text_seq_length=8, use_rotary_positional_embeddings=True,
        use_learned_positional_embeddings=True,
    )
    transformer.save_pretrained(root / "transformer")
    t5 = T5EncoderModel(T5Config(vocab_size=30522, d_model=32, d_kv=8, d_ff=64, num_layers=1, num_heads=2))
    t5.save_pretrained(root / "text_encoder")
    AutoTokenizer.from_pretrained(minilm_path()).save_pretrained(root / "tokenizer")
    return root


def short_step_budget(monkeypatch, module: str, seconds_per_call: float = 1.0):
    """The trainer's StepBudget with a short probe (1 untimed, 2 timed steps) on a clock that moves
    ``seconds_per_call`` each time it is read, so the fitted number of steps is known in advance."""
    import functools
    import importlib

    now = [0.0]

    def clock():
        now[0] += seconds_per_call
        return now[0]

    monkeypatch.setattr(importlib.import_module(module), "StepBudget",
                        functools.partial(StepBudget, skip_steps=1, timed_steps=2, clock=clock))


def sigterm_after_step(monkeypatch, trainer, step: int) -> None:
    """Send this process SIGTERM right after ``trainer`` finishes training step ``step`` (a
    scheduler's stop arriving mid-run); any trainer with ``train_step()`` and ``step``, or a trainer
    class (every instance, e.g. the one a command builds)."""
    import os
    import signal

    def stop_after(obj, logs):
        if obj.step == step:
            os.kill(os.getpid(), signal.SIGTERM)
        return logs

    train_step = trainer.train_step
    if isinstance(trainer, type):
        monkeypatch.setattr(trainer, "train_step", lambda self: stop_after(self, train_step(self)))
    else:
        monkeypatch.setattr(trainer, "train_step", lambda: stop_after(trainer, train_step()))
