"""Fine-tuning a few-step student on its own previous clips (Self-Forcing style), for long rollouts.

A rollout longer than one clip conditions each next clip on the last frame the model predicted
(``pipeline.py``), while the model was only ever trained on true first frames: the second clip starts
from a frame it never saw (a smeared object, a torn arm). Here the student meets that frame in training.

1. **Conditions** (:func:`sample_self_forced`, no gradient, cached once): for every chained episode
   of a dataset (datagen ``--set chain_skills=2``: segment 1 is frames 0..15 under instruction 1,
   segment 2 the next clip under instruction 2), the student samples clip 1 from the true frame 0 and
   instruction 1 with its own sampler (one draw, the pipeline's ``__call__``), and the clip's last
   decoded frame, as the pipeline hands it to the next clip (model space, after static compositing,
   re-encoded by the next clip), is cached as the **self-forced condition**. Beside it: the true frame
   at the same place (the control's condition), the true next clip in the network's space (the
   target), and the student's own clip 1 as a reflow pair (noise, true frame 0, its latent clip).
2. **Fine-tuning** (:class:`SelfForcingTrainer`): the student's own loss (``denoising_loss``: the clean
   clip from ``x_t = (1 - t) x0 + t noise``) toward the TRUE next clip with instruction 2, conditioned
   on the cached self-forced frame (``condition="self"``) or on the true frame (``condition="true"``,
   the control: same steps, data, loss and learning rate). ``t`` is drawn from the student's own
   sampling noise levels only (``times="sampler"``; its 2-step flow-matching Euler sampler runs the
   network at 1.0 and 0.001), the only inputs its network meets at sampling, or ``t ~ U(0, 1)``
   (``times="uniform"``, as ``distill`` trains).
   A share of each batch (``own_share``) is the student's own clip-1 reflow pairs, trained as
   ``distill`` trains them, so it keeps its straight noise-to-clip paths and its 2-step sampling (the
   teacher pairs it was distilled from are not kept with the checkpoint).

Cache and fine-tune (the run folder is a ``distill`` run folder; ``RUN/final`` an inference checkpoint)::

    python -m tesseract4d.model.self_forcing cache --checkpoint tesseract4d/checkpoints/v2-2step \
        --data data/train_chain2 --out runs/sf/conditions.pt
    python -m tesseract4d.model.self_forcing train --checkpoint tesseract4d/checkpoints/v2-2step \
        --conditions runs/sf/conditions.pt --out runs/sf/self --set condition=self --set max_steps=200

The cache (``torch.save``) holds ``episode_ids``, ``instructions`` (E pairs of words),
``self_condition`` and ``true_condition`` (E, 7, H, W) float16 model space, ``target`` (E, t', c, h, w)
float16 network space, ``own_first`` (E, 7, H, W), ``own_noise`` and ``own_x0`` (E, t', c, h, w), the
checkpoint, its weights digest, the noise seed and the sampler's settings.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from tesseract4d import dataset_format as df
from tesseract4d.configs import folder_list, with_overrides
from tesseract4d.errors import UserError
from tesseract4d.instruction_schedule import schedule_of
from tesseract4d.model.checkpoint import weights_digest
from tesseract4d.model.pipeline import RGBDNPipeline, make_scheduler
from tesseract4d.model.predict import load_pipeline
from tesseract4d.model.predicted_latents import save_cache
from tesseract4d.model.reflow import ReflowConfig, ReflowTrainer, model_space_psnr
from tesseract4d.model.trainer import Trainer
from tesseract4d.training.config import option

BATCH = 4  # chains per pipeline call
CONDITIONS = ("self", "true")
TIMES = ("sampler", "uniform")


def _noise_generator(noise_seed: int, index: int) -> torch.Generator:
    return torch.Generator().manual_seed(int(noise_seed) * 1_000_003 + int(index))


@torch.no_grad()
def self_forced_frames(pipe: RGBDNPipeline, first: torch.Tensor, words: list[str], noise: torch.Tensor,
                       generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """The student's clip 1 from ``first`` (b, 7, H, W) and ``words`` with initial ``noise``: (the frame the
    pipeline hands to the next clip, (b, 7, H, W) model space; the clip's latent (b, t', c, h, w)). The clip
    is sampled once, by the pipeline's own ``__call__``, and finished as the pipeline finishes a clip
    (``finish_clip``: the first-frame decoder, static compositing as the preset sets it)."""
    z = pipe(first, words, latents=noise, generator=generator, output_type="latent")  # (b, t', c, h, w)
    clip = pipe.finish_clip(z, first.float(), pipe.preset.static_tolerance)  # (b, T, 7, H, W)
    return clip[:, -1].float().cpu(), z.float()


def sample_self_forced(checkpoint: Path, folders: list[Path], noise_seed: int = 0, camera: str | None = None,
                       precision: str = "auto", log=print) -> dict:
    """The cache's dict (module docstring) for every chained episode of ``folders`` with at least 2 segments
    whose second clip lies inside the episode."""
    files = [f for folder in folders for f in df.list_episode_files(folder)]
    pipe = load_pipeline(checkpoint, precision=precision)
    T = pipe.num_frames
    chains = []
    for path in files:
        ep = df.read_episode(path)
        segments = schedule_of(ep.metadata)
        name = camera or pipe.camera_name or next(iter(ep.cameras))
        if name not in ep.cameras:
            raise UserError(f"{path} has no camera {name!r}; it has {sorted(ep.cameras)}: pass --camera")
        cam = ep.cameras[name]
        if segments is None or len(segments) < 2:
            continue
        start = T - 1  # where the pipeline's second clip starts (instruction_schedule.clip_new_frames)
        if segments[1].frame_start != start or ep.num_frames < start + T:
            raise UserError(f"{path}: its second segment starts at frame {segments[1].frame_start} of "
                            f"{ep.num_frames}; self-forcing needs chains whose second segment is the rollout's "
                            f"second clip, frames {start}..{start + T - 1}: `tesseract4d datagen --set "
                            f"chain_skills=2 --frames {2 * start + 1}`")
        if tuple(cam.rgb.shape[1:3]) != tuple(pipe.resolution):
            raise UserError(f"{path} is {cam.rgb.shape[1]}x{cam.rgb.shape[2]}; the checkpoint predicts "
                            f"{pipe.resolution[0]}x{pipe.resolution[1]}")
        frames = pipe.model_space.encode(cam.rgb[:start + T], cam.depth_m[:start + T], cam.normal_cam[:start + T])
        chains.append((ep.episode_id, frames, segments[0].instruction, segments[1].instruction))
    if not chains:
        raise UserError(f"{', '.join(map(str, folders))} hold no chained episodes; write some with `tesseract4d "
                        f"datagen --tasks Tesseract4dTabletop-v1 --set chain_skills=2 --frames {2 * (T - 1) + 1}`")
    out = {k: [] for k in ("self_condition", "target", "own_noise", "own_x0")}
    t0 = time.time()
    for b in range(0, len(chains), BATCH):
        chunk = chains[b:b + BATCH]
        first = torch.stack([c[1][0] for c in chunk])
        noise = torch.cat([torch.randn(pipe.latent_shape(1), generator=_noise_generator(noise_seed, b + i))
                           for i in range(len(chunk))])
        cond, z = self_forced_frames(pipe, first, [c[2] for c in chunk], noise,
                                     _noise_generator(noise_seed, 10_000_000 + b))
        with torch.no_grad():
            target = pipe.codec.encode(torch.stack([c[1][T - 1:2 * T - 1] for c in chunk]).to(pipe.device)).cpu()
        for k, v in (("self_condition", cond), ("target", target), ("own_noise", noise), ("own_x0", z)):
            out[k].append(v.half())
        log(f"{b + len(chunk)}/{len(chains)} chains ({(time.time() - t0) / (b + len(chunk)):.2f} s a chain)")
    return {"episode_ids": [c[0] for c in chains], "instructions": [(c[2], c[3]) for c in chains],
            **{k: torch.cat(v) for k, v in out.items()},
            "true_condition": torch.stack([c[1][T - 1] for c in chains]).half(),
            "own_first": torch.stack([c[1][0] for c in chains]).half(),
            "checkpoint": str(checkpoint), "digest": weights_digest(checkpoint), "noise_seed": int(noise_seed),
            "num_steps": pipe.preset.num_steps, "static_tolerance": pipe.preset.static_tolerance,
            "data": [str(f) for f in folders]}


class SelfForcedChains:
    """A cache file of :func:`sample_self_forced` in memory."""

    def __init__(self, path: Path):
        path = Path(path)
        if not path.is_file():
            raise UserError(f"{path} does not exist; write it with `python -m tesseract4d.model.self_forcing cache`")
        saved = torch.load(path, map_location="cpu")
        self.path = path
        self.manifest = {k: v for k, v in saved.items() if not isinstance(v, torch.Tensor)}
        self.instructions = [tuple(w) for w in saved["instructions"]]
        for k in ("self_condition", "true_condition", "target", "own_first", "own_noise", "own_x0"):
            setattr(self, k, saved[k])
        self.camera = None

    def __len__(self) -> int:
        return len(self.instructions)

    def condition(self, which: str) -> torch.Tensor:
        """(E, 7, H, W) conditions of the second clip: the student's own last frame, or the true one."""
        return self.self_condition if which == "self" else self.true_condition


@dataclass
class SelfForcingConfig(ReflowConfig):
    """Options of the self-forcing fine-tune; ``data`` is the cache file, ``teacher`` the student itself
    (the run starts from its weights)."""

    condition: str = option("self", "the second clip's condition: 'self' (the student's own last frame, cached) "
                                    "or 'true' (the true frame: the control)")
    own_share: float = option(0.5, "share of each batch from the student's own clip-1 reflow pairs (keeps its "
                                   "few-step sampling)")
    times: str = option("sampler", "diffusion times of the second clips: 'sampler' (the student's own sampling noise "
                                   "levels only) or 'uniform' (t ~ U(0, 1), as distill trains)")


def sampling_levels(num_steps: int) -> torch.Tensor:
    """The noise levels at which a ``num_steps`` flow-matching Euler sampler runs the network (1.0 first)."""
    scheduler = make_scheduler()
    scheduler.set_timesteps(num_steps)
    return torch.as_tensor(scheduler.sigmas[:-1], dtype=torch.float32)


class SelfForcingTrainer(ReflowTrainer):
    """The student fine-tuned on its own previous clips (module docstring): a ``distill`` run folder."""

    cfg: SelfForcingConfig

    def __init__(self, config: SelfForcingConfig):
        if config.condition not in CONDITIONS:
            raise UserError(f"condition must be one of {', '.join(CONDITIONS)}, got {config.condition!r}")
        if config.times not in TIMES:
            raise UserError(f"times must be one of {', '.join(TIMES)}, got {config.times!r}")
        if not 0.0 <= config.own_share < 1.0:
            raise UserError(f"own_share must be in [0, 1), got {config.own_share}")
        super().__init__(config)
        self.levels = sampling_levels(self.preset.num_steps)

    def _build_data(self, cfg) -> SelfForcedChains:
        data = SelfForcedChains(Path(cfg.data))
        if data.manifest.get("digest") != self.teacher_digest:
            raise UserError(f"{cfg.data} holds the clips of other weights ({data.manifest.get('digest')}); the "
                            f"student {cfg.teacher} has {self.teacher_digest}: cache its own clips")
        data.camera = self.teacher_config.get("camera_name")  # the student's: the cache was sampled with it
        p = self.preset
        if tuple(data.self_condition.shape[-2:]) != (p.height, p.width):
            raise UserError(f"{cfg.data} holds {tuple(data.self_condition.shape[-2:])} frames; the student predicts "
                            f"{(p.height, p.width)}")
        return data

    def _check_group_data(self) -> None:
        raise UserError("the self-forcing fine-tune draws chains, not counterfactual groups; leave group_batches off")

    def batch(self, step: int):
        """Step ``step``'s batch: (x0, condition frames (b, 7, H, W), texts, t, noise); the first
        ``b - round(b * own_share)`` items are second clips (true target, the configured condition, t at
        the student's sampling levels, fresh noise), the rest the student's own clip-1 pairs (t ~ U(0, 1))."""
        cfg, data = self.cfg, self.data
        g = self._step_generator(step)
        n_own = int(round(cfg.batch_size * cfg.own_share))
        n_sf = cfg.batch_size - n_own
        i = torch.randint(len(data), (n_sf,), generator=g)
        j = torch.randint(len(data), (n_own,), generator=g)
        x0 = torch.cat([data.target[i], data.own_x0[j]]).float()
        cond = torch.cat([data.condition(cfg.condition)[i], data.own_first[j]]).float()
        texts = [data.instructions[k][1] for k in i.tolist()] + [data.instructions[k][0] for k in j.tolist()]
        t_sf = (self.levels[torch.randint(len(self.levels), (n_sf,), generator=g)] if cfg.times == "sampler"
                else torch.rand(n_sf, generator=g))
        t = torch.cat([t_sf, torch.rand(n_own, generator=g)])
        noise = torch.cat([torch.randn((n_sf, *x0.shape[1:]), generator=g), data.own_noise[j].float()])
        return x0, cond, texts, t, noise

    def compute_loss(self, step: int) -> tuple[torch.Tensor, dict[str, float]]:
        x0, cond, texts, t, noise = self.batch(step)
        first_enc = self.codec.encode(cond[:, None].to(self.device))  # (b, 1, c, h, w), as the pipeline encodes it
        text = self.text_encoder.encode(texts)  # (b, L, d)
        return self.denoising_loss(x0, first_enc, text, t, noise)

    def _inference_config(self) -> dict:
        cfg = Trainer._inference_config(self)
        m = self.data.manifest
        cfg["self_forcing"] = {"student": str(self.cfg.teacher), "student_digest": self.teacher_digest,
                               "conditions": str(self.cfg.data), "chains": len(self.data),
                               "condition": self.cfg.condition, "own_share": self.cfg.own_share,
                               "times": self.cfg.times,
                               "noise_seed": m.get("noise_seed"), "data": m.get("data"),
                               "levels": [round(float(s), 4) for s in self.levels]}
        return cfg

    def validation_indices(self) -> list[int]:
        return list(range(min(self.cfg.val_clips, len(self.data))))

    def validate(self) -> dict[str, float]:
        """PSNR (model space, all channels) of the EMA student's second clips from the self-forced
        condition against the true ones."""
        idx = self.validation_indices()
        if not idx:
            return {}
        pipe = RGBDNPipeline(self.ema.model, make_scheduler(), self.codec, self.text_encoder, self.preset,
                             self.model_space, bf16=self.precision.bf16)
        first = self.data.self_condition[idx].float()
        texts = [self.data.instructions[i][1] for i in idx]
        z = pipe(first, texts, output_type="latent", generator=torch.Generator().manual_seed(0))
        self.ema.model.eval()
        return {"val/psnr_self_forced_vs_true": model_space_psnr(self.codec, z, self.data.target[idx].float())}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="Self-forcing fine-tune of a few-step student on its own previous clips.")
    sub = p.add_subparsers(dest="what", required=True)
    c = sub.add_parser("cache", help="sample and cache the student's self-forced conditions of chained episodes")
    c.add_argument("--checkpoint", type=Path, required=True)
    c.add_argument("--data", type=Path, nargs="+", required=True, help="chained dataset folders (chain_skills=2)")
    c.add_argument("--noise-seed", type=int, default=0)
    c.add_argument("--camera", default=None, help="camera of --data (default: the checkpoint's)")
    c.add_argument("--out", type=Path, required=True, help="file to write (refused if it exists)")
    t = sub.add_parser("train", help="fine-tune the student on the cache (or the control with --set condition=true)")
    t.add_argument("--checkpoint", type=Path, required=True, help="the student (its cache's checkpoint)")
    t.add_argument("--conditions", type=Path, required=True, help="the cache file")
    t.add_argument("--out", type=Path, required=True, help="the run folder")
    t.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="a SelfForcingConfig field")
    a = p.parse_args(argv)
    if a.what == "cache":
        if a.out.exists():
            raise UserError(f"{a.out} exists; choose another --out (it is not overwritten)")
        cache = sample_self_forced(a.checkpoint, folder_list(a.data), a.noise_seed, a.camera,
                                   log=lambda m: print(m, flush=True))
        save_cache(cache, a.out)
        print(f"wrote {a.out}: {len(cache['episode_ids'])} chains")
        return 0
    cfg = SelfForcingConfig(teacher=a.checkpoint, data=a.conditions, out=a.out, val_every=0)
    cfg = with_overrides(cfg, dict(item.split("=", 1) for item in a.set))
    final = SelfForcingTrainer(cfg).train()
    print(f"wrote {final}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
