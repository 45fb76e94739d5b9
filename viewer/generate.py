"""The live generation behind the viewer's Generate button: predict + reconstruct.

:func:`model_generator` returns a ``generate(instruction, seed, steps, progress) -> Recon4D``
callable (see ``viewer.app.Generator``) that conditions the model on frame 0 of the loaded
source. The model loads on the first click, not at start-up. A future longer than one clip streams:
each clip's last frame goes to ``progress`` as its third argument as soon as the clip is decoded.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

from reconstruction.recon4d import Recon4D
from reconstruction.reconstruct import ReconConfig, reconstruct_episode
from tesseract4d.errors import UserError
from tesseract4d.model.checkpoint import read_inference_config
from viewer.sources import first_frame_episode

# Share of the progress bar spent denoising; the rest is reconstruction.
PREDICT_SHARE = 0.8


def checkpoint_steps(checkpoint: str | os.PathLike) -> int:
    """The sampler steps a checkpoint's preset uses (read from its config; the model is not loaded)."""
    return int(read_inference_config(checkpoint)["preset"]["num_steps"])


def model_generator(checkpoint: str | os.PathLike, source: Recon4D,
                    precision: str = "auto") -> Callable[[str, int, int, Callable[[float, str], None]], Recon4D]:
    """``precision``: auto|fp32|bf16 for the model (tesseract4d/precision.py)."""
    checkpoint = Path(checkpoint)
    if not checkpoint.is_dir():
        raise UserError(f"checkpoint {checkpoint} not found; pass --checkpoint DIR (a folder written by `tesseract4d train`).")
    cache: dict = {}

    def generate(instruction: str, seed: int, steps: int, progress: Callable[[float, str], None]) -> Recon4D:
        # deferred: imports torch (heavy)
        from tesseract4d.model.predict import load_pipeline, predict_episode

        if "pipeline" not in cache:
            progress(0.0, f"loading {checkpoint}")
            cache["pipeline"] = load_pipeline(checkpoint, precision=precision)
        first = first_frame_episode(source)
        # A source of one frame (a first frame alone) gets the model's own clip length.
        num_frames = source.num_frames if source.num_frames > 1 else None
        done = [0.0]  # the share of the denoising finished, for the streamed frames' progress line

        def step_done(step: int, total: int) -> None:
            done[0] = PREDICT_SHARE * step / max(total, 1)
            progress(done[0], denoising_message(step, total, steps))

        def clip_done(k: int, so_far) -> None:  # streaming: show each clip's last frame as it is decoded
            cam = next(iter(so_far.cameras.values()))
            progress(done[0], f"clip {k + 1} decoded: frames 0–{so_far.num_frames - 1}", cam.rgb[-1])

        long_future = num_frames is not None and num_frames > cache["pipeline"].num_frames  # more than one clip
        pred = predict_episode(cache["pipeline"], first, instruction, num_frames=num_frames, seed=seed, num_steps=steps,
                               progress=step_done, on_clip=clip_done if long_future else None)
        progress(PREDICT_SHARE, "reconstructing the 4D point cloud")
        recon = reconstruct_episode(pred, config=ReconConfig(), objects_from=first)  # objects named as in the source
        recon.metadata.update({"instruction": instruction, "sample_seed": seed, "steps": steps})
        return recon

    return generate


def denoising_message(step: int, total: int, steps: int) -> str:
    """The progress line of denoising step ``step`` of ``total``: the sampler runs its ``steps`` once
    per noise draw (and per clip of a future longer than the model's), each run a pass."""
    passes = max(1, total // max(steps, 1))
    if passes == 1:
        return f"denoising step {step}/{total}"
    return f"denoising step {(step - 1) % steps + 1}/{steps} of pass {(step - 1) // steps + 1}/{passes}"
