"""Test helpers of the model tests: a synthetic RGB-D-N dataset, a micro preset, a tiny random
CogVideoX-5B-I2V-shaped model folder."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from tesseract4d import dataset_format as df
from tesseract4d.model.presets import CONDITION_REPEAT, PIXEL, PRESETS, ModelPreset

MICRO = ModelPreset(
    "micro", PIXEL, 32, 32, 8, CONDITION_REPEAT, "minilm", 8,
    backbone=dict(num_attention_heads=2, attention_head_dim=16, num_layers=2, time_embed_dim=32, text_embed_dim=384,
                  max_text_seq_length=8, sample_width=32, sample_height=32, sample_frames=8, patch_size=4,
                  patch_size_t=2, temporal_compression_ratio=1, use_rotary_positional_embeddings=True,
                  use_learned_positional_embeddings=False),
    lr=2e-3, warmup_steps=5, batch_size=2, ema_decay=0.9, text_dropout=0.1, image_dropout=0.05,
    num_steps=4, text_guidance=1.0, image_guidance=1.0,
)

INSTRUCTIONS = {1: "push the square to the right", -1: "push the square to the left"}


def synthetic_episode(seed: int, frames: int = 8, size: int = 32, direction: int = 1) -> df.Episode:
    """A square moving sideways in front of a tilted plane: RGB, metric depth, normals, K."""
    rng = np.random.default_rng(seed)
    f = size * 1.0
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], np.float64)
    v, u = np.mgrid[0:size, 0:size]
    plane_depth = (0.9 + 0.3 * v / size).astype(np.float32)
    plane_normal = np.array([0.0, -0.3, -1.0], np.float32)
    plane_normal /= np.linalg.norm(plane_normal)
    colour = rng.integers(120, 256, 3)
    x0, y0 = int(rng.integers(4, size // 2)), int(rng.integers(6, size - 14))
    rgb = np.zeros((frames, size, size, 3), np.uint8)
    depth = np.zeros((frames, size, size), np.float32)
    normal = np.zeros((frames, size, size, 3), np.float32)
    for t in range(frames):
        rgb[t] = (40 + 100 * v[..., None] / size).astype(np.uint8)
        depth[t] = plane_depth
        normal[t] = plane_normal
        x = x0 + direction * t
        rgb[t, y0:y0 + 8, x:x + 8] = colour
        depth[t, y0:y0 + 8, x:x + 8] = 0.5
        normal[t, y0:y0 + 8, x:x + 8] = (0.0, 0.0, -1.0)
    cam = df.CameraFrames(rgb=rgb, depth_m=depth, normal_cam=normal, K=np.repeat(K[None], frames, 0),
                          T_world_cam=np.repeat(np.eye(4)[None], frames, 0))
    return df.Episode(env_id="Synthetic-v0", seed=seed, instruction=INSTRUCTIONS[direction], cameras={"close": cam},
                      frame_steps=np.arange(frames, dtype=np.int32), success=True)


def write_synthetic_dataset(root: Path, episodes: int = 4, frames: int = 8, size: int = 32) -> Path:
    df.init_dataset(root, df.DatasetInfo(height=size, width=size, cameras=["close"]))
    for seed in range(episodes):
        df.write_episode(root, synthetic_episode(seed, frames, size, direction=1 if seed % 2 == 0 else -1))
    return root


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

    from tesseract4d.model.text_encoder import minilm_path

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


SEGMENTS = {0: "background", 17: "ground", 18: "cube"}


def write_segmented_dataset(root: Path, episodes: int = 3, frames: int = 8, size: int = 32) -> Path:
    """The synthetic moving-square dataset with a segmentation: square = 'cube', plane = 'ground'."""
    df.init_dataset(root, df.DatasetInfo(height=size, width=size, cameras=["close"]))
    for seed in range(episodes):
        ep = synthetic_episode(seed, frames, size, direction=1 if seed % 2 == 0 else -1)
        cam = ep.cameras["close"]
        cam.segmentation = np.where(np.isclose(cam.depth_m, 0.5), 18, 17).astype(np.int32)
        cam.seg_id_to_name = dict(SEGMENTS)
        df.write_episode(root, ep)
    return root
