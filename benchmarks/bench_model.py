"""Benchmark the RGB-D-N model: training steps/s and sampling seconds per clip, fp32 vs bf16.

The first line names the CPU model and ISA and the precision `--precision auto` picks on it: bf16
speed differs by an order of magnitude between CPUs with and without native bf16 (see tesseract4d/precision.py).

Training: the trainer's own step (batch of clips, forward, loss, backward, grad clip, AdamW, EMA) on
synthetic clips of the preset's size. Sampling: one clip of the preset's length through the
pipeline (flow-match Euler) at 10/25/50 steps, with the preset's guidance (text guidance 1.5 = two
network passes per step) and without guidance (one pass). Peak memory is the process's peak
resident set size during each measurement (VmHWM, reset before it). Weights are random: speed does
not depend on them.

  .venv/bin/python benchmarks/bench_model.py [--presets tiny,tiny-128] [--train-steps 6] [--batch-size 4]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from measure import add_isa_cap_argument, apply_isa_cap, machine_line, print_table


def _reset_peak_rss() -> None:
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def _peak_rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def bench_training(preset_name: str, data: Path, bf16: bool, steps: int, batch_size: int) -> dict:
    from tesseract4d.model.trainer import TrainConfig, Trainer

    with tempfile.TemporaryDirectory() as out:
        trainer = Trainer(TrainConfig(data=data, out=Path(out), preset=preset_name, max_steps=steps + 1,
                                      precision="bf16" if bf16 else "fp32",
                                      batch_size=batch_size, val_every=0, ckpt_every=0, quiet=True))
        trainer.train_step()  # warm-up (allocations, text encoding)
        _reset_peak_rss()
        times = []
        for _ in range(steps):
            t0 = time.perf_counter()
            trainer.train_step()
            times.append(time.perf_counter() - t0)
        return {"s_per_step": statistics.median(times), "peak_mb": _peak_rss_mb()}


def sampling_pipeline(preset_name: str, bf16: bool, autoencoder: Path | None = None):
    """A pipeline of the preset with random transformer weights (a latent preset decodes with
    ``autoencoder``), warmed up, and a random first frame: what the sampling rows time."""
    import torch

    from tesseract4d.model.build import build_codec, build_text_encoder, build_transformer
    from tesseract4d.model.model_space import ModelSpace
    from tesseract4d.model.pipeline import RGBDNPipeline, make_scheduler
    from tesseract4d.model.presets import get_preset

    preset = get_preset(preset_name)
    codec = build_codec(preset, autoencoder=autoencoder)
    torch.manual_seed(0)
    pipe = RGBDNPipeline(build_transformer(preset, codec), make_scheduler(), codec, build_text_encoder(preset), preset,
                         ModelSpace(preset.near_m, preset.far_m), bf16=bf16)
    first = torch.rand(1, 7, preset.height, preset.width) * 2 - 1
    pipe(first, ["pick up the red cube"], num_inference_steps=1)  # warm-up
    return pipe, first


def time_clip(pipe, first, steps: int, guided: bool, seed: int) -> float:
    """Seconds for one clip at ``steps`` steps, with the preset's text guidance or without."""
    import torch

    kw = dict(num_inference_steps=steps, text_guidance=pipe.preset.text_guidance if guided else 1.0, image_guidance=1.0)
    t0 = time.perf_counter()
    pipe(first, ["pick up the red cube"], generator=torch.Generator().manual_seed(seed), **kw)
    return time.perf_counter() - t0


def bench_sampling(preset_name: str, bf16: bool, steps: int, guided: bool, repeats: int) -> dict:
    pipe, first = sampling_pipeline(preset_name, bf16)
    _reset_peak_rss()
    times = [time_clip(pipe, first, steps, guided, r) for r in range(repeats)]
    return {"s_per_clip": statistics.median(times), "peak_mb": _peak_rss_mb()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--presets", default="tiny", help="comma-separated pixel presets (default %(default)s)")
    parser.add_argument("--train-steps", type=int, default=6, help="timed training steps per setting")
    parser.add_argument("--batch-size", type=int, default=4)
    parser.add_argument("--sample-steps", default="10,25,50")
    parser.add_argument("--repeats", type=int, default=3, help="timed clips per sampling setting")
    add_isa_cap_argument(parser)
    args = parser.parse_args(argv)
    apply_isa_cap(args.cap_isa)

    from tesseract4d import runtime

    runtime.configure()
    from tesseract4d.testing.synthetic_scene import write_synthetic_dataset

    from tesseract4d.model.presets import get_preset

    from tesseract4d.precision import resolve_precision

    auto = resolve_precision("auto", "cpu", warn=False)
    print(machine_line(f"--precision auto -> {auto.name}"))
    rows = []
    for name in args.presets.split(","):
        preset = get_preset(name)
        with tempfile.TemporaryDirectory() as tmp:
            data = write_synthetic_dataset(Path(tmp) / "data", episodes=4, frames=preset.num_frames, size=preset.height)
            for bf16 in (False, True):
                r = bench_training(name, data, bf16, args.train_steps, args.batch_size)
                rows.append((name, "bf16" if bf16 else "fp32", f"train b{args.batch_size}",
                             f"{1 / r['s_per_step']:.2f} steps/s ({r['s_per_step']:.2f} s/step)", f"{r['peak_mb']:.0f}"))
                print(*rows[-1], sep=" | ", flush=True)
        for bf16 in (False, True):
            for steps in [int(s) for s in args.sample_steps.split(",")]:
                for guided in (True, False):
                    r = bench_sampling(name, bf16, steps, guided, args.repeats)
                    label = f"sample {steps} steps, " + (f"text guidance {preset.text_guidance}" if guided else "no guidance")
                    rows.append((name, "bf16" if bf16 else "fp32", label,
                                 f"{r['s_per_clip']:.2f} s/clip ({preset.num_frames} frames)", f"{r['peak_mb']:.0f}"))
                    print(*rows[-1], sep=" | ", flush=True)
    header = ("preset", "precision", "what", "speed", "peak RSS MB")
    print()
    print(machine_line())
    print_table(header, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
