"""Few-step sampling with one network pass per step, by rectified-flow reflow.

Reflow ("Flow straight and fast", Liu et al. 2022) in two stages:

1. **Pairs** (:func:`generate_pairs`): the teacher, a trained checkpoint, samples clips with its full
   sampler (its preset's steps and classifier-free guidance) from stored noise. Each
   (noise, first frame, instruction) -> teacher clip is one pair, kept in the network's space.
   With ``groups``, pairs come as whole counterfactual groups (one scene under several
   instructions) that share one noise, so a group's pairs differ only by the words.
2. **Student** (``tesseract4d distill``, the trainer's reflow mode): initialised with the teacher's
   weights, it learns the straight path between the two ends of each pair,
   ``x_t = (1 - t) x_teacher + t noise`` with target ``x_teacher``, conditioned on the first frame
   and the text only. Straight paths are integrated almost exactly by a few Euler steps, and the
   target is the *guided* teacher's output, so the student samples in 1-4 steps without guidance:
   one network pass per step instead of two. On grouped pairs the student can train with the
   teacher's counterfactual swap (``recipe.swap_sources``): at diffusion time >= ``SWAP_MIN_T`` a
   pair is shown, with probability ``counterfactual_swap``, a sibling's noisy sample and must still
   reach its own teacher clip, so the student keeps reading the future from the words.

A pairs folder holds ``pairs-XXXXX.safetensors`` shards (``first`` (n, 7, H, W) model space,
``noise`` and ``x0`` (n, t', c, h, w) network space; with groups also ``leader`` (n,): the shard
position of each pair's group's first pair), a JSON sidecar per shard with its instructions, and
``reflow_pairs.json`` (the teacher, its sampler settings and the data). Shards are written whole
(temporary file, then rename), so an interrupted run resumes at the next shard. The sidecars also name
each pair's episode and clip start.
"""

from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch

from tesseract4d.configs import config_dict, folder_list, knob, plain
from tesseract4d.errors import UserError
from tesseract4d.outputs import check_not_input, files_as_created
from tesseract4d.model.checkpoint import read_inference_config, weights_digest
from tesseract4d.model.trainer import TrainConfig, Trainer
from tesseract4d.precision import precision_field
from tesseract4d.training.config import option
from tesseract4d.model.presets import PRESETS, preset_from_dict
from tesseract4d.model.clips import (
    ClipDataset, dataset_units, draw_group_batch, grouped_batch_plan, merge_clip_datasets,
)
from tesseract4d.model.predict import load_pipeline
from tesseract4d.model.recipe import share_within_groups, swap_sources
from tesseract4d.psnr import rgb_psnr
from tesseract4d.model.pipeline import RGBDNPipeline, make_scheduler

MANIFEST = "reflow_pairs.json"
SHARD_PREFIX = "pairs-"


@dataclass
class PairsConfig:
    teacher: Path = knob(help="inference checkpoint folder of the teacher", metavar="CKPT")
    data: Path | list[Path] = knob(help="dataset folder(s) the pairs' first frames and instructions come from",
                                   metavar="DIR")
    out: Path = knob(help="pairs folder (written, or resumed, from --data)", metavar="PAIRS")
    num_pairs: int = knob(512, "teacher clips to sample")
    shard_size: int = knob(32, "pairs per shard file")
    batch_size: int = knob(4, "teacher clips per sampler call")
    teacher_steps: int | None = knob(None, "the teacher's sampler steps (none: its preset's)")
    text_guidance: float | None = knob(None, "the teacher's text guidance scale (none: its preset's; 1 = none)")
    image_guidance: float | None = knob(None, "the teacher's first-frame guidance scale (none: its preset's)")
    seed: int = knob(0, "seed of the pairs' noise")
    camera: str | None = knob(None, "camera of --data (none: the teacher's)")
    precision: str = precision_field()
    groups: bool = knob(False, "draw the pairs as whole counterfactual groups of --data (one scene under several "
                               "instructions), a group's pairs sharing one noise")

    def to_dict(self) -> dict:
        return config_dict(self)


def _shard_path(out: Path, index: int) -> Path:
    return out / f"{SHARD_PREFIX}{index:05d}.safetensors"


# What a manifest written before a key existed meant by it: pairs before guidance intervals were
# guided at every step. Also the removed teacher options (autoguidance, teacher draws) at the values
# that made them no-ops: this version makes pairs only so, and refuses pairs made otherwise.
_MANIFEST_DEFAULTS = {"guidance_min_sigma": 0.0, "autoguidance": 0.0, "teacher_draws": 1}


def _check_manifest(out: Path, manifest: dict) -> None:
    path = out / MANIFEST
    if not path.is_file():
        if out.exists() and any(out.iterdir()):
            raise UserError(f"--pairs {out} holds files that are not reflow pairs; choose a new or empty --pairs folder")
        return
    saved = json.loads(path.read_text())
    keys = ("teacher_digest", "teacher_steps", "text_guidance", "image_guidance", "guidance_min_sigma", "autoguidance",
            "data", "seed", "shard_size", "groups", "teacher_draws")
    differ = [k for k in keys if saved.get(k, _MANIFEST_DEFAULTS.get(k))
              != manifest.get(k, _MANIFEST_DEFAULTS.get(k))]
    if differ:
        raise UserError(f"{out} holds pairs made with other settings ({', '.join(differ)} differ); "
                        f"choose a new --pairs folder for these settings")


def check_pairs_of_teacher(pairs: Path, teacher: Path, teacher_steps: int | None = None,
                           text_guidance: float | None = None) -> None:
    """Refuse pairs (a ``--pairs`` folder reused without ``--data``) that ``teacher`` did not make:
    other weights, or a sampler its settings fix (image guidance, guidance interval: ``set-sampler``
    copies share weights but not these), or made with a removed option (autoguidance, teacher draws);
    the steps and text guidance the pairs were
    made with (recorded in the student's ``distilled_from``) only when given. Reads configs and
    digests only, no weights into memory."""
    saved = json.loads((Path(pairs) / MANIFEST).read_text())
    p = preset_from_dict(read_inference_config(teacher)["preset"])
    now = {"teacher_digest": weights_digest(teacher), "image_guidance": p.image_guidance,
           "guidance_min_sigma": p.guidance_min_sigma, "autoguidance": 0.0, "teacher_draws": 1,
           **({} if teacher_steps is None else {"teacher_steps": teacher_steps}),
           **({} if text_guidance is None else {"text_guidance": text_guidance})}
    differ = [k for k, v in now.items() if saved.get(k, _MANIFEST_DEFAULTS.get(k)) != v]
    if differ:
        raise UserError(f"--pairs {pairs} holds pairs that {teacher} did not make as it samples now "
                        f"({', '.join(differ)} differ); pass the teacher that made them, or --data DIR to make "
                        f"new pairs into a new --pairs folder")


def generate_pairs(cfg: PairsConfig, progress: bool = True) -> Path:
    """Sample ``cfg.num_pairs`` teacher clips into ``cfg.out`` (resumes at the first missing shard)."""
    from safetensors.torch import save_file
    from tqdm import tqdm

    if cfg.num_pairs < 1 or cfg.shard_size < 1 or cfg.batch_size < 1:
        raise UserError("--num-pairs and --pair-batch-size must be at least 1 (and the shard size of the pairs)")
    # On a GPU machine the teacher samples there, as the trainers train there (CUDA_VISIBLE_DEVICES= keeps it on the CPU).
    pipe = load_pipeline(cfg.teacher, device="cuda" if torch.cuda.is_available() else "cpu", precision=cfg.precision)
    p = pipe.preset
    steps = cfg.teacher_steps or p.num_steps
    text_g = p.text_guidance if cfg.text_guidance is None else cfg.text_guidance
    image_g = p.image_guidance if cfg.image_guidance is None else cfg.image_guidance
    data = merge_clip_datasets([ClipDataset(folder, num_frames=p.num_frames, height=p.height, width=p.width,
                                            model_space=pipe.model_space, camera=cfg.camera or pipe.camera_name)
                                for folder in folder_list(cfg.data)])
    if cfg.groups:
        dataset_units(data)  # refuses data without counterfactual groups
    out = Path(cfg.out)
    manifest = {"format": 1, "teacher": str(cfg.teacher), "teacher_digest": weights_digest(cfg.teacher),
                "teacher_preset": p.to_dict(), "teacher_steps": steps, "text_guidance": text_g,
                "image_guidance": image_g, "guidance_min_sigma": p.guidance_min_sigma, "data": plain(cfg.data),
                "camera": data.camera, "seed": cfg.seed, "shard_size": cfg.shard_size, "groups": bool(cfg.groups), "config": cfg.to_dict()}
    _check_manifest(out, manifest)
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / f".{MANIFEST}.tmp"
    tmp.write_text(json.dumps(manifest, indent=2))
    os.replace(tmp, out / MANIFEST)

    num_shards = -(-cfg.num_pairs // cfg.shard_size)
    bar = tqdm(total=cfg.num_pairs, desc="reflow pairs", unit="clip", disable=not progress)
    for s in range(num_shards):
        n = min(cfg.shard_size, cfg.num_pairs - s * cfg.shard_size)
        path = _shard_path(out, s)
        if path.is_file() and path.with_suffix(".json").is_file():
            bar.update(n)
            continue
        # Every shard's batch and noise depend only on (seed, shard): a resumed run makes the same pairs.
        g = _shard_generator(cfg.seed, s)
        indices, starts, leaders = _shard_plan(data, n, g, cfg.groups)
        drawn = [data.clip(i, st) for i, st in zip(indices, starts)]
        first = torch.stack([c[0] for c, _ in drawn])  # (n, 7, H, W)
        texts = [t for _, t in drawn]
        noise = share_within_groups(torch.randn(pipe.latent_shape(n), generator=g), leaders)

        x0 = []
        for i in range(0, n, cfg.batch_size):
            sl = slice(i, i + cfg.batch_size)
            x0.append(pipe(first[sl], texts[sl], num_inference_steps=steps, text_guidance=text_g,
                           image_guidance=image_g, latents=noise[sl], output_type="latent", generator=g))
            bar.update(len(texts[sl]))
        x0 = torch.cat(x0).float().cpu()
        tensors = {"first": first.half().contiguous(), "noise": noise.contiguous(), "x0": x0.contiguous()}
        if leaders is not None:
            tensors["leader"] = torch.tensor(leaders, dtype=torch.int64)
        tmp_st = path.with_name(f".{path.name}.tmp")
        save_file(tensors, str(tmp_st))
        files_as_created(tmp_st)  # safetensors writes 0600
        tmp_js = path.with_name(f".{path.stem}.json.tmp")
        record = {"instructions": texts, "episodes": [data.sources[i].episode_id for i in indices], "starts": starts}
        tmp_js.write_text(json.dumps(record))
        os.replace(tmp_st, path)
        os.replace(tmp_js, path.with_suffix(".json"))
    bar.close()
    return out


def _shard_generator(seed: int, shard: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed * 1_000_003 + shard)


def _shard_plan(data, n: int, generator: torch.Generator, groups: bool) -> tuple[list[int], list[int], list[int] | None]:
    """A shard's episode indices, clip starts and (grouped) group leaders: the shard's first draws."""
    if groups:
        return grouped_batch_plan(data, n, generator)  # whole groups
    return (*data.batch_plan(n, generator), None)


def _complete_shards(folder: Path) -> list[Path]:
    shards = sorted(Path(folder).glob(f"{SHARD_PREFIX}*.safetensors"))
    return [s for s in shards if s.with_suffix(".json").is_file()]


def count_pairs(folder: str | os.PathLike) -> int:
    """The pairs in the complete shards of ``folder`` (from their sidecars: no tensors read)."""
    return sum(len(json.loads(s.with_suffix(".json").read_text())["instructions"]) for s in _complete_shards(folder))


class ReflowPairs:
    """The pairs of a folder written by :func:`generate_pairs`, in memory.

    ``sample_batch(b, generator)`` returns (first (b, 7, H, W), noise, x0 (b, t', c, h, w), texts);
    on grouped pairs ``sample_group_batch`` also each pair's group leader (its batch position).
    """

    def __init__(self, folder: str | os.PathLike):
        from safetensors.torch import load_file

        self.folder = Path(folder)
        path = self.folder / MANIFEST
        if not path.is_file():
            raise UserError(f"{self.folder} is not a reflow pairs folder (no {MANIFEST}); make one with "
                            f"`tesseract4d distill --pairs-only --teacher CKPT --data DIR --pairs {self.folder}`")
        self.manifest = json.loads(path.read_text())
        shards = _complete_shards(self.folder)
        if not shards:
            raise UserError(f"{self.folder} holds no complete pair shard yet; run the pair generation first")
        parts, self.instructions = [], []
        for s in shards:
            parts.append(load_file(str(s)))
            self.instructions += json.loads(s.with_suffix(".json").read_text())["instructions"]
        self.first = torch.cat([p["first"] for p in parts])
        self.noise = torch.cat([p["noise"] for p in parts])
        self.x0 = torch.cat([p["x0"] for p in parts])
        self.camera = self.manifest.get("camera")
        # Each pair's group as the index of its group's first pair (shard positions made global), and
        # the pairs of each group, worked out once rather than in every training step.
        self.grouped = bool(self.manifest.get("groups")) and all("leader" in p for p in parts)
        self.group_of: list[int] = []
        offset = 0
        for p in parts:
            n = p["first"].shape[0]
            leader = p["leader"].tolist() if "leader" in p else list(range(n))
            self.group_of += [offset + k for k in leader]
            offset += n
        units: dict[int, list[int]] = {}
        for i, leader in enumerate(self.group_of):
            units.setdefault(leader, []).append(i)
        self._units = list(units.values())

    def __len__(self) -> int:
        return len(self.instructions)

    def sample_batch(self, batch_size: int, generator: torch.Generator):
        idx = torch.randint(len(self), (batch_size,), generator=generator)
        texts = [self.instructions[i] for i in idx.tolist()]
        return self.first[idx].float(), self.noise[idx], self.x0[idx], texts

    def group_units(self) -> list[list[int]]:
        """The pairs of each group (a pair outside a group alone); a UserError for pairs made without groups."""
        if not self.grouped:
            raise UserError(f"{self.folder} holds pairs drawn one by one; the counterfactual swap needs pairs of whole "
                            f"groups: make them with `tesseract4d distill --set groups=true` in a new --pairs folder")
        return self._units

    def sample_group_batch(self, batch_size: int, generator: torch.Generator):
        """Like :meth:`sample_batch`, of whole groups (:func:`clips.draw_group_batch`), plus each pair's
        group leader (its batch position)."""
        units = self.group_units()
        idx, _, leaders = draw_group_batch(units, [1] * len(self), 1, batch_size, generator)
        texts = [self.instructions[i] for i in idx]
        return self.first[idx].float(), self.noise[idx], self.x0[idx], texts, leaders


# --------------------------------------------------------------------------- the student

@dataclass
class ReflowConfig(TrainConfig):
    """Options of the student's training (`tesseract4d distill`). ``data`` is the pairs folder;
    the preset, model space, text encoder and initial weights are the teacher's."""

    teacher: Path | None = option(None, "the teacher's inference checkpoint folder")
    student_steps: int = option(2, "the student's sampler steps (its preset's num_steps), one network pass each")
    max_steps: int | str = option(1000, "the student's optimiser steps; the cosine learning-rate decay ends here")
    val_every: int = option(100, "PSNR of the student against the teacher every N steps (0: never)")
    val_clips: int = option(4, "pairs the validation compares")


def student_preset(teacher_preset, student_steps: int):
    """The teacher's preset with the student's sampling defaults: ``student_steps`` Euler steps and no
    guidance (text = image = 1.0), i.e. one network pass per step. The teacher's
    static compositing (``static_tolerance``, on decoded frames, after the network) is kept: the pairs
    are latents, which it never touches."""
    return dataclasses.replace(teacher_preset, num_steps=int(student_steps), text_guidance=1.0, image_guidance=1.0,
                               guidance_min_sigma=0.0, text_dropout=0.0, image_dropout=0.0)


class ReflowTrainer(Trainer):
    """Trains a few-step student on teacher pairs with the trainer's own loss (``denoising_loss``):
    ``x_t = (1 - t) x0_teacher + t noise`` with the pair's noise, target the teacher's clip, no
    text or first-frame dropout. Starts from the teacher's weights; validation compares the
    student's K-step samples with the teacher's outputs of the same noise."""

    cfg: ReflowConfig
    command = "distill"

    def __init__(self, config: ReflowConfig, paraphrases: Callable[[str], list[str]] | None = None):
        if config.teacher is None:
            raise UserError("pass --teacher CKPT (the inference checkpoint to distil)")
        if config.student_steps < 1:
            raise UserError(f"student_steps must be at least 1, got {config.student_steps}")
        check_not_input(config.out, [config.teacher], "--out")
        self.teacher_config = read_inference_config(config.teacher)
        # The student inherits, for a latent preset, the teacher's autoencoder (the copy inside the
        # teacher checkpoint, hash-checked); it sees the clean first frame, as at sampling.
        config = dataclasses.replace(config, text_dropout=0.0, image_dropout=0.0, condition_noise=0.0, text_noise=0.0,
                                     init=config.teacher,
                                     pretrained=config.pretrained or self.teacher_config.get("pretrained_dir"))
        super().__init__(config, paraphrases)

    @property
    def teacher_digest(self) -> str:
        """The teacher's weights digest: the run's start (``init``), hashed once by the trainer."""
        return self.init_digest

    def _resolve_preset(self, config: TrainConfig):
        teacher = preset_from_dict(self.teacher_config["preset"])
        if teacher.name not in PRESETS:
            raise UserError(f"{config.teacher} uses preset {teacher.name!r}, unknown to this tesseract4d")
        return student_preset(teacher, config.student_steps)

    def _build_data(self, cfg: TrainConfig) -> ReflowPairs:
        pairs = ReflowPairs(cfg.data)
        made_by = pairs.manifest.get("teacher_digest")
        if made_by != self.teacher_digest:
            raise UserError(f"{cfg.data} holds pairs of another teacher (weights {made_by}, --teacher has "
                            f"{self.teacher_digest}); make pairs of this teacher in a new --pairs folder")
        p = self.preset
        if tuple(pairs.first.shape[-2:]) != (p.height, p.width):
            raise UserError(f"{cfg.data} holds {tuple(pairs.first.shape[-2:])} first frames; the teacher predicts "
                            f"{(p.height, p.width)}")
        return pairs

    def _check_group_data(self) -> None:
        self.data.group_units()

    def compute_loss(self, step: int) -> tuple[torch.Tensor, dict[str, float]]:
        cfg = self.cfg
        g = self._step_generator(step)
        leaders = shown = None
        if cfg.group_batches:
            first, noise, x0, texts, leaders = self.data.sample_group_batch(cfg.batch_size, g)
        else:
            first, noise, x0, texts = self.data.sample_batch(cfg.batch_size, g)
        first_enc = self.codec.encode(first[:, None].to(self.device), generator=g)  # (b, 1, c, h, w)
        text = self.text_encoder.encode(self.rephrased(texts, g))  # (b, L, d)
        t = share_within_groups(torch.rand(x0.shape[0], generator=g), leaders)
        if leaders is not None and cfg.counterfactual_swap > 0:
            shown = swap_sources(leaders, t, cfg.counterfactual_swap, g)
        return self.denoising_loss(x0, first_enc, text, t, noise, shown=shown)

    def _inference_config(self) -> dict:
        m = self.data.manifest
        cfg = super()._inference_config()
        cfg["distilled_from"] = {
            "method": "rectified-flow reflow", "teacher": str(self.cfg.teacher), "teacher_digest": self.teacher_digest,
            "teacher_steps": m.get("teacher_steps"), "text_guidance": m.get("text_guidance"),
            "image_guidance": m.get("image_guidance"), "pairs": str(self.cfg.data), "num_pairs": len(self.data),
            "pair_groups": bool(m.get("groups")), "student_steps": self.preset.num_steps}
        return cfg

    def validation_indices(self) -> list[int]:
        """The first ``val_clips`` pairs (the same ones at every validation)."""
        return list(range(min(self.cfg.val_clips, len(self.data))))

    def validate(self) -> dict[str, float]:
        """PSNR (model space, all 7 channels) of the student's K-step samples (EMA weights) against the
        teacher's clips from the same noise."""
        idx = self.validation_indices()
        if not idx:
            return {}
        pipe = RGBDNPipeline(self.ema.model, make_scheduler(), self.codec, self.text_encoder, self.preset,
                             self.model_space, camera_name=self.data.camera, bf16=self.precision.bf16)
        first, noise, x0 = self.data.first[idx].float(), self.data.noise[idx], self.data.x0[idx]
        texts = [self.data.instructions[i] for i in idx]
        student = pipe(first, texts, latents=noise, output_type="latent")  # the student preset's steps, no guidance
        self.ema.model.eval()
        return {"val/psnr_student_vs_teacher": model_space_psnr(self.codec, student, x0)}


def model_space_psnr(codec, a: torch.Tensor, b: torch.Tensor) -> float:
    """PSNR (dB, peak 1) of two network-space batches decoded to model space ([-1, 1] -> [0, 1], all
    channels: RGB, depth, normal)."""
    with torch.no_grad():
        da = ((codec.decode(a.float()) + 1) / 2).clamp(0, 1)
        db = ((codec.decode(b.float()) + 1) / 2).clamp(0, 1)
    return rgb_psnr(da.cpu(), db.cpu())  # the student's batch may be on a GPU
