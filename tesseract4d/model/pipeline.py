"""The RGB-D-N sampling pipeline, in the style of diffusers' CogVideoX image-to-video pipeline.

Inference only: the transformer predicts the clean clip (x0_hat, "first frame + correction"), the
flow-matching scheduler (``FlowMatchEulerDiscreteScheduler``) owns the noise math. Rectified flow:
``x_t = (1 - t) x0 + t noise``; the scheduler steps along the velocity ``v = (x_t - x0_hat) / t``.

Classifier-free guidance on text and first frame (InstructPix2Pix-style, on x0_hat):
``x0 = uncond + s_img (img - uncond) + s_txt (full - img)``, where ``img`` has the first frame but
no text and ``uncond`` has neither. Passes that a guidance scale of 1 makes unnecessary are skipped.

Static compositing (``static_tolerance`` > 0, ``static_composite.py``): where the decoded clip does not
change from its frame 0, the given first frame's own pixels are put back, so the still part of the
scene is shown as given instead of as the decoder redraws it.

Clips longer than the preset's clip continue autoregressively: each next clip is conditioned on the
last frame predicted so far, or on the last k frames (``history_frames`` k > 1, a model trained for it:
the clip's first k frames are that history and its other ``num_frames - k`` are new). An instruction schedule gives each clip its own words (``clip_instructions``,
see tesseract4d/instruction_schedule.py), and ``on_clip`` receives each clip's new frames as soon as
it is decoded (streaming).
"""

from __future__ import annotations

from typing import Callable

import torch

from tesseract4d.instruction_schedule import clip_new_frames
from tesseract4d.model.codec import make_condition
from tesseract4d.model.presets import ModelPreset
from tesseract4d.model.static_composite import composite_static

def make_scheduler():
    """The few-step sampler: flow-matching Euler over sigmas 1 -> 0."""
    from diffusers import FlowMatchEulerDiscreteScheduler

    return FlowMatchEulerDiscreteScheduler(num_train_timesteps=1000, shift=1.0)


def guidance_passes(text_guidance: float, image_guidance: float) -> tuple[str, ...]:
    """The conditionings one sampler step batches into one network forward: "full" (first frame and
    text), then "image" (first frame, no text) when any guidance is on, then "none" (neither) when
    first-frame guidance is on. A guidance scale of 1 needs no pass of its own."""
    passes = ("full",)
    if text_guidance != 1.0 or image_guidance != 1.0:
        passes += ("image",)
    if image_guidance != 1.0:
        passes += ("none",)
    return passes


class RGBDNPipeline:
    """First frame + instruction -> RGB-D-N clip, all in model space (see model_space.py).

    Components: ``transformer`` (RGBDNTransformer), ``scheduler`` (a diffusers flow-matching
    scheduler), ``codec`` (PixelCodec / VaeCodec), ``text_encoder`` (TextEncoder). ``bf16``: run the transformer under bf16
    autocast (resolved by tesseract4d.precision from auto|fp32|bf16); fp32 otherwise.
    """

    def __init__(self, transformer, scheduler, codec, text_encoder, preset: ModelPreset, model_space,
                 camera_name: str | None = None, bf16: bool = False, config: dict | None = None):
        self.transformer = transformer.eval()
        self.scheduler = scheduler
        self.codec = codec
        self.text_encoder = text_encoder
        self.preset = preset
        self.model_space = model_space
        self.camera_name = camera_name
        self.bf16 = bf16
        self.config = config or {}  # the checkpoint's tesseract4d_config.json, when loaded from one
        self.device = next(transformer.parameters()).device

    @property
    def resolution(self) -> tuple[int, int]:
        return (self.preset.height, self.preset.width)

    @property
    def num_frames(self) -> int:
        return self.preset.num_frames

    def to(self, device: str | torch.device) -> "RGBDNPipeline":
        self.device = torch.device(device)
        self.transformer.to(self.device)
        self.codec.to(self.device)
        return self

    def _forward(self, x_t, conditions, texts, sigma, history_frames: int = 1):
        """One batched forward of the transformer over the conditionings stacked along the batch:
        one x0_hat per conditioning."""
        n = len(conditions)
        extra = {} if history_frames == 1 else {"history_frames": history_frames}
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.bf16):
            out = self.transformer(x_t.repeat(n, 1, 1, 1, 1), torch.cat(conditions), torch.cat(texts),
                                   torch.full((n * x_t.shape[0],), float(sigma), device=self.device), **extra).float()
        return out.split(x_t.shape[0])

    def _predict_x0(self, x_t, sigma, cond, null_cond, text, null_text, text_guidance, image_guidance,
                    history_frames: int = 1):
        """Guided x0_hat (b, t', c, h, w) for the current noisy sample."""
        inputs = {"full": (cond, text), "image": (cond, null_text), "none": (null_cond, null_text)}
        passes = [inputs[name] for name in guidance_passes(text_guidance, image_guidance)]
        preds = self._forward(x_t, [p[0] for p in passes], [p[1] for p in passes], sigma, history_frames)
        if len(preds) == 1:
            guided = preds[0]
        elif len(preds) == 2:
            guided = preds[1] + text_guidance * (preds[0] - preds[1])
        else:
            full, img, uncond = preds
            guided = uncond + image_guidance * (img - uncond) + text_guidance * (full - img)
        return guided

    def latent_shape(self, batch: int) -> tuple[int, ...]:
        """Shape of one clip's initial noise in the network's space: (b, t', c, h, w)."""
        p = self.preset
        probe = self.codec.encode(torch.zeros(1, 1, 7, p.height, p.width, device=self.device))  # (1, 1, c, h, w)
        return (batch, self.codec.num_latent_frames(p.num_frames), *probe.shape[2:])

    def _denoise_clip(self, first_frame, text, null_text, num_steps, text_guidance, image_guidance,
                      generator, progress, step_offset, total_steps, latents=None, guidance_min_sigma=0.0,
                      start=None, history=None):
        """One clip of the preset's length from a (b, 7, H, W) first frame, in the network's space:
        (b, t', c, h, w). ``history``: (b, k, 7, H, W) model-space frames the clip continues from (its
        first k frames; ``first_frame`` is then history[:, 0]); default: the first frame alone.
        ``latents``: the initial noise (default: drawn from ``generator``).
        ``guidance_min_sigma``: steps at a lower noise level run unguided (one pass).
        ``start``: (clean clips (b, t', c, h, w), sigma): begin at the first noise level ``s`` ≤ sigma
        from ``(1 - s) clean + s noise`` and run only the steps from there."""
        b = first_frame.shape[0]
        nt = self.codec.num_latent_frames(self.preset.num_frames)
        given = first_frame[:, None] if history is None else history  # (b, k, 7, H, W)
        first = self.codec.encode(given.to(self.device), generator=generator)  # (b, k, c, h, w)
        history_frames = first.shape[1]
        cond = make_condition(first, nt, self.preset.condition)
        null_cond = torch.zeros_like(cond)
        if latents is None:
            # Noise on the CPU generator so a seed gives the same clip on every device.
            x = torch.randn((b, nt, *first.shape[2:]), generator=generator, dtype=torch.float32).to(self.device)
        else:
            if tuple(latents.shape) != (b, nt, *first.shape[2:]):
                raise ValueError(f"latents must be {(b, nt, *first.shape[2:])}, got {tuple(latents.shape)}")
            x = latents.float().to(self.device)
        self.scheduler.set_timesteps(num_steps, device=self.device)
        first_step = 0
        if start is not None:
            clean, start_sigma = start
            if tuple(clean.shape) != tuple(x.shape):
                raise ValueError(f"start clips must be {tuple(x.shape)}, got {tuple(clean.shape)}")
            levels = [float(s) for s in self.scheduler.sigmas[:-1]]
            first_step = next((i for i, s in enumerate(levels) if s <= start_sigma), len(levels) - 1)
            s = levels[first_step]
            x = (1.0 - s) * clean.float().to(self.device) + s * x
        for i, timestep in enumerate(self.scheduler.timesteps):
            if i >= first_step:
                sigma = float(self.scheduler.sigmas[i])
                guided = sigma >= guidance_min_sigma
                pred = self._predict_x0(x, sigma, cond, null_cond, text, null_text,
                                        text_guidance if guided else 1.0, image_guidance if guided else 1.0,
                                        history_frames)
                velocity = (x - pred) / sigma
                x = self.scheduler.step(velocity, timestep, x, return_dict=False)[0]
            if progress is not None:
                progress(step_offset + i + 1, total_steps)
        return x

    @torch.no_grad()
    def decode(self, z: torch.Tensor, first_frame: torch.Tensor | None = None) -> torch.Tensor:
        """Network-space clips (b, t', c, h, w) -> fp32 model-space clips (b, T, 7, H, W) in [-1, 1],
        in the pipeline's precision. ``first_frame`` (b, 7, H, W): the clips' given first frames, read by
        a decoder that reads them (first_frame_decoder.py; other codecs ignore it)."""
        # A latent codec's decoder is a fifth to a tenth of a clip's time; bf16 decodes it in about
        # 60 % of fp32's time (benchmarks/bench_latent.py).
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.bf16):
            if first_frame is not None and getattr(self.codec, "reads_first_frame", False):
                return self.codec.decode(z, first_frame=first_frame.to(self.device)).float().clamp(-1.0, 1.0)
            return self.codec.decode(z).float().clamp(-1.0, 1.0)

    def finish_clip(self, z: torch.Tensor, first_frame: torch.Tensor, static_tolerance: float = 0.0) -> torch.Tensor:
        """A sampled network-space clip (b, t', c, h, w) as the pipeline hands it on: decoded (b, T, 7, H, W)
        model space, and with ``static_tolerance`` > 0 the first frame put back where the clip is still
        (static_composite.py)."""
        clip = self.decode(z, first_frame=first_frame)
        if static_tolerance > 0:
            clip = composite_static(clip, first_frame, static_tolerance)
        return clip

    def _sample_clip(self, first_frame, *args, static_tolerance: float = 0.0, **kwargs):
        """One decoded clip (b, T, 7, H, W) in model space; arguments as :meth:`_denoise_clip`, then
        :meth:`finish_clip`."""
        return self.finish_clip(self._denoise_clip(first_frame, *args, **kwargs), first_frame, static_tolerance)

    @torch.no_grad()
    def __call__(
        self,
        first_frame: torch.Tensor,
        instructions: list[str],
        *,
        num_frames: int | None = None,
        num_inference_steps: int | None = None,
        text_guidance: float | None = None,
        image_guidance: float | None = None,
        guidance_min_sigma: float | None = None,
        static_tolerance: float | None = None,
        generator: torch.Generator | None = None,
        progress: Callable[[int, int], None] | None = None,
        latents: torch.Tensor | None = None,
        output_type: str = "clip",
        start: tuple[torch.Tensor, float] | None = None,
        clip_instructions: list[list[str]] | None = None,
        on_clip: Callable[[int, torch.Tensor], None] | None = None,
        history_frames: int | None = None,
    ) -> torch.Tensor:
        """Sample a batch of clips.

        first_frame: (b, 7, H, W) model-space first frames; instructions: b strings (one per sample).
        num_frames: frames to return (default: one clip); longer rollouts continue autoregressively.
        guidance_min_sigma: guide only the steps at noise levels ≥ it; the steps below run one unguided
        pass (default: the preset's; 0 = every step guided).
        static_tolerance: put the given first frame back where the decoded clip stays within this
        (model-space units) of its frame 0 (static_composite.py; 0 = off; default: the preset's).
        generator: a CPU ``torch.Generator``; the same seed gives the same clips.
        progress: optional callable(step, total) called after every denoising step.
        latents: the first clip's initial noise (b, t', c, h, w) (see :meth:`latent_shape`); default:
        drawn from ``generator``.
        output_type: "clip" (decoded frames) or "latent": the first clip's final sample in the
        network's space, (b, t', c, h, w), before decoding (one clip only; static compositing acts on
        decoded frames, so not on these).
        start: a diagnostic, one clip only: (clean clips in the network's space (b, t', c, h, w), such
        as a true future through ``codec.encode``, and a noise level 0 < sigma ≤ 1): the sampler begins
        at its first noise level ``s`` ≤ sigma (its last, if none is) from ``(1 - s) clips + s noise``
        and runs only the steps from there; how much of a right future the network keeps.
        clip_instructions: per clip of the rollout (``instruction_schedule.clip_new_frames``), one
        instruction per sample: clip k is sampled with ``clip_instructions[k]`` (an instruction
        schedule); default: ``instructions`` for every clip.
        on_clip: called as ``on_clip(k, frames)`` once clip k is decoded, with the frames it adds to
        the rollout, (b, n, 7, H, W) on the CPU (frame 0 included for clip 0): frames can be shown or
        written while the next clip is sampled.
        history_frames: k, how many of the last frames so far each clip after the first continues from
        (default: the preset's, which the model was trained for; 1: the last frame alone).
        Returns (b, num_frames, 7, H, W) model-space clips; frame 0 is the model's reconstruction
        of the first frame (the first frame itself with static compositing on).
        """
        # 1. Check inputs.
        p = self.preset
        num_frames = p.num_frames if num_frames is None else int(num_frames)
        num_steps = p.num_steps if num_inference_steps is None else int(num_inference_steps)
        text_guidance = p.text_guidance if text_guidance is None else float(text_guidance)
        image_guidance = p.image_guidance if image_guidance is None else float(image_guidance)
        guidance_min_sigma = p.guidance_min_sigma if guidance_min_sigma is None else float(guidance_min_sigma)
        static_tolerance = p.static_tolerance if static_tolerance is None else float(static_tolerance)
        history_frames = p.history_frames if history_frames is None else int(history_frames)
        b = first_frame.shape[0]
        if first_frame.ndim != 4 or tuple(first_frame.shape[2:]) != self.resolution:
            raise ValueError(f"first_frame must be (b, 7, {p.height}, {p.width}), got {tuple(first_frame.shape)}")
        if len(instructions) != b:
            raise ValueError(f"{len(instructions)} instructions for {b} first frames")
        if num_frames < 1 or num_steps < 1:
            raise ValueError("num_frames and num_inference_steps must be >= 1")
        if not static_tolerance >= 0:
            raise ValueError(f"static_tolerance must be >= 0 (0 = off), got {static_tolerance}")
        if output_type not in ("clip", "latent"):
            raise ValueError(f"output_type must be 'clip' or 'latent', got {output_type!r}")
        if output_type == "latent" and num_frames != p.num_frames:
            raise ValueError("output_type='latent' returns exactly one clip; leave num_frames at the preset's")
        if start is not None and (num_frames != p.num_frames or not 0.0 < float(start[1]) <= 1.0):
            raise ValueError("start needs exactly one clip (num_frames at the preset's) and a noise level in (0, 1]")
        if not 1 <= history_frames < p.num_frames:
            raise ValueError(f"history_frames must be 1 .. {p.num_frames - 1}, got {history_frames}")
        if history_frames > 1 and self.codec.temporal_compression != 1:
            raise ValueError("history_frames > 1 needs a codec with one latent frame per frame (not a video VAE)")
        new_frames = clip_new_frames(num_frames, p.num_frames, history_frames)
        if clip_instructions is not None:
            if len(clip_instructions) != len(new_frames) or any(len(c) != b for c in clip_instructions):
                raise ValueError(f"clip_instructions must hold {len(new_frames)} clips of {b} instructions each")
            if output_type == "latent" or start is not None:
                raise ValueError("clip_instructions schedule a rollout of decoded clips; not with output_type='latent' "
                                 "or start")
        generator = generator if generator is not None else torch.Generator().manual_seed(0)

        # 2. Encode the instructions (cached per instruction): one text batch per clip.
        text = self.text_encoder.encode(list(instructions)).to(self.device)
        null_text = torch.zeros_like(text)
        texts = [text] * len(new_frames)
        if clip_instructions is not None:
            texts = [self.text_encoder.encode(list(words)).to(self.device) for words in clip_instructions]

        if output_type == "latent":
            return self._denoise_clip(first_frame.float(), text, null_text, num_steps, text_guidance, image_guidance,
                                      generator, progress, 0, num_steps, latents=latents,
                                      guidance_min_sigma=guidance_min_sigma, start=start).cpu()

        # 3. Sample clip after clip, each conditioned on the last history_frames frames so far (the first
        # clip on the first frame alone), with its words.
        num_clips = len(new_frames)
        total = num_clips * num_steps
        frames = []
        history = first_frame.float()[:, None]  # (b, k, 7, H, W)
        for k in range(num_clips):
            clip = self._sample_clip(history[:, 0], texts[k], null_text, num_steps, text_guidance, image_guidance,
                                     generator, progress, k * num_steps, total,
                                     latents=latents if k == 0 else None,
                                     guidance_min_sigma=guidance_min_sigma, start=start,
                                     static_tolerance=static_tolerance,
                                     history=history if history.shape[1] > 1 else None).cpu()
            given = history.shape[1] if k > 0 else 0
            frames.append(clip[:, given:given + len(new_frames[k]) + (1 if k == 0 else 0)])
            if on_clip is not None:
                on_clip(k, frames[-1])
            if k + 1 < num_clips:
                history = torch.cat(frames, dim=1)[:, -history_frames:]
        # 4. Stitch the clips.
        return torch.cat(frames, dim=1)[:, :num_frames]
