"""A cache of the latents a checkpoint predicts for dataset episodes, before decoding.

The first-frame decoder (first_frame_decoder.py) is trained on latents; a decoder that only ever saw
the truth's latents meets other latents at prediction time (a smeared object, the arm elsewhere). This
module samples, for each episode of some datasets, the checkpoint's latent clip from the episode's true
first frame and its own instruction, one clip per noise seed, without decoding it, and stores it with
the episode's path so the truth's frames and segmentation can be read beside it::

    python -m tesseract4d.model.predicted_latents --checkpoint tesseract4d/checkpoints/v2-2step \
        --data data/train_tabletop data/train_cubes --noise-seeds 0 1 --out runs/pred_latents.pt

The file (``torch.save``) holds ``episode_ids`` and ``episode_files`` (E), ``noise_seeds`` (S),
``latents`` (E, S, T, C, h, w) float16 normalised latents (the network's space: what
``codec.decode`` reads), the checkpoint's folder and autoencoder digest, and the sampler's settings.
Noise seed s draws the initial noise that ``predict_scenes(noise_seeds=[s])`` draws for its first
draw, one draw per seed (no best-of-draws choice: the choice reads decoded frames).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from tesseract4d import dataset_format as df
from tesseract4d.configs import folder_list
from tesseract4d.errors import UserError
from tesseract4d.model.predict import load_pipeline

BATCH = 4  # scenes per pipeline call (predict.py's DEFAULT_SCENE_BATCH measured 4 within 7 % of the best)


def sample_predicted_latents(checkpoint: Path, folders: list[Path], noise_seeds: list[int],
                             camera: str | None = None, precision: str = "auto", log=print) -> dict:
    """The cache's dict (module docstring) for every episode of ``folders``."""
    files = [f for folder in folders for f in df.list_episode_files(folder)]
    if not files:
        raise UserError(f"{', '.join(map(str, folders))} hold no episodes; write some with `tesseract4d datagen`")
    if not noise_seeds:
        raise UserError("give at least one noise seed (--noise-seeds 0 1)")
    pipe = load_pipeline(checkpoint, precision=precision)
    firsts, words, ids = [], [], []
    for path in files:
        ep = df.read_episode(path)
        cam = ep.cameras[camera or next(iter(ep.cameras))]  # as the decoder's training reads it (load_clips)
        if tuple(cam.rgb.shape[1:3]) != tuple(pipe.resolution):
            raise UserError(f"{path} is {cam.rgb.shape[1]}x{cam.rgb.shape[2]}; the checkpoint predicts "
                            f"{pipe.resolution[0]}x{pipe.resolution[1]}: use datasets of its resolution")
        firsts.append(pipe.model_space.encode(cam.rgb[:1], cam.depth_m[:1], cam.normal_cam[:1]))  # (1, 7, H, W)
        words.append(ep.instruction)
        ids.append(ep.episode_id)
    noise_shape = pipe.latent_shape(1)  # (1, t', c, h, w)
    per_seed = []
    t0 = time.time()
    for s in noise_seeds:
        out = []
        for b in range(0, len(files), BATCH):
            chunk = range(b, min(len(files), b + BATCH))
            noise = torch.cat([torch.randn(noise_shape, generator=torch.Generator().manual_seed(int(s))) for _ in chunk])
            z = pipe(torch.cat([firsts[i] for i in chunk]), [words[i] for i in chunk], latents=noise,
                     generator=torch.Generator().manual_seed(int(s) + b), output_type="latent")  # (b, t', c, h, w)
            out.append(z.half())
            log(f"noise seed {s}: {min(len(files), b + BATCH)}/{len(files)} episodes "
                f"({(time.time() - t0) / (len(per_seed) * len(files) + b + len(chunk)):.2f} s a clip)")
        per_seed.append(torch.cat(out))
    return {"episode_ids": ids, "episode_files": [str(f) for f in files], "noise_seeds": [int(s) for s in noise_seeds],
            "latents": torch.stack(per_seed, dim=1),  # (E, S, T, C, h, w)
            "checkpoint": str(checkpoint), "autoencoder_hash": getattr(pipe.codec, "autoencoder_hash", ""),
            "num_steps": pipe.preset.num_steps, "text_guidance": pipe.preset.text_guidance,
            "image_guidance": pipe.preset.image_guidance}


def load_predicted_latents(path: Path, episode_ids: list[str]) -> torch.Tensor:
    """(E, S, T, C, h, w) float16 latents of ``path`` in the order of ``episode_ids``; refused with the fix
    when the file lacks one of them."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path} does not exist; write it with `python -m tesseract4d.model.predicted_latents`")
    saved = torch.load(path, map_location="cpu")
    index = {e: i for i, e in enumerate(saved["episode_ids"])}
    missing = [e for e in episode_ids if e not in index]
    if missing:
        raise UserError(f"{path} holds no predicted latents for {len(missing)} training episodes (e.g. {missing[0]}); "
                        f"sample it from the same --data")
    return saved["latents"][[index[e] for e in episode_ids]]


def save_cache(cache: dict, out: Path) -> None:
    """``torch.save`` of a cache to ``out`` through a temporary file, so a stopped write leaves no half file."""
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    torch.save(cache, tmp)
    tmp.replace(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Sample a checkpoint's latent clips of dataset episodes (no decoding).")
    p.add_argument("--checkpoint", type=Path, required=True, help="inference checkpoint (e.g. tesseract4d/checkpoints/v2-2step)")
    p.add_argument("--data", type=Path, nargs="+", required=True, help="dataset folders")
    p.add_argument("--noise-seeds", type=int, nargs="+", default=[0, 1], help="one latent clip per episode and seed")
    p.add_argument("--out", type=Path, required=True, help="file to write (refused if it exists)")
    p.add_argument("--camera", default=None)
    a = p.parse_args(argv)
    if a.out.exists():
        raise UserError(f"{a.out} exists; choose another --out (it is not overwritten)")
    cache = sample_predicted_latents(a.checkpoint, folder_list(a.data), a.noise_seeds, a.camera,
                                     log=lambda m: print(m, flush=True))
    save_cache(cache, a.out)
    print(f"wrote {a.out}: latents {tuple(cache['latents'].shape)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
