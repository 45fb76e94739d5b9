"""Benchmark the latent world model at 128²: autoencoder and latent model, against the pixel ``tiny``.

Rows (each with precision and the process's peak resident memory, VmHWM, reset before it):
- autoencoder encode / decode of one 16-frame 128² clip;
- autoencoder training steps/s (the trainer's own step, batch 8 frames);
- latent model (``latent-128``) training steps/s at batch 4, reading a latent cache, and ``tiny`` beside it;
- seconds per 16-frame clip at 10 steps with text guidance (two passes per step), decode included,
  for ``latent-128`` (with each autoencoder) and ``tiny``, timed in turns (one clip of each per
  round; the memory column is then the peak of all of them together), so that the drift of a
  shared machine falls on every entry alike: the comparison is between these rows.
Weights are random (speed does not depend on them) unless --autoencoder names a trained one.
bf16 rows run only where the CPU has AMX or AVX512-BF16 (elsewhere bf16 is far slower).

  .venv/bin/python benchmarks/bench_latent.py [--autoencoder-preset ae-f8c32] [--repeats 3]
  .venv/bin/python benchmarks/bench_latent.py --autoencoder AE [AE ...]   # trained ones, side by side (numbered in order)
  .venv/bin/python benchmarks/bench_latent.py --guidance-min-sigma 0.5      # also with a guidance interval
  .venv/bin/python benchmarks/bench_latent.py --no-training --repeats 20    # the sampling comparison alone
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import tempfile
from pathlib import Path

from bench_model import _peak_rss_mb, _reset_peak_rss, bench_training, sampling_pipeline, time_clip
from measure import add_isa_cap_argument, apply_isa_cap, machine_line, median_seconds, print_table


def bench_autoencoder_codec(ae_dir: Path, bf16: bool, repeats: int) -> dict:
    import torch

    from tesseract4d.model.autoencoder_loading import load_autoencoder
    from tesseract4d.model.codec import AutoencoderCodec

    codec = AutoencoderCodec(load_autoencoder(ae_dir))  # as the pipeline and the latent cache use it
    cfg = codec.autoencoder.config
    x = torch.rand(1, 16, 7, cfg.height, cfg.width) * 2 - 1  # one 16-frame clip
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        z = codec.encode(x)
        _reset_peak_rss()
        enc = median_seconds(lambda: codec.encode(x), repeats)
        dec = median_seconds(lambda: codec.decode(z), repeats)
    return {"encode_s": enc, "decode_s": dec, "peak_mb": _peak_rss_mb(),
            "decoder": f"{cfg.layers_per_block + 1}-resnet decoder blocks"}


def bench_autoencoder_training(data: Path, preset: str, bf16: bool, steps: int) -> dict:
    from tesseract4d.model.autoencoder_trainer import AutoencoderTrainConfig, AutoencoderTrainer

    with tempfile.TemporaryDirectory() as out:
        trainer = AutoencoderTrainer(AutoencoderTrainConfig(data=data, out=Path(out) / "run", preset=preset,
                                                            precision="bf16" if bf16 else "fp32", quiet=True))
        trainer.train_step()
        _reset_peak_rss()
        s = median_seconds(trainer.train_step, steps)
        return {"s_per_step": s, "peak_mb": _peak_rss_mb()}


def bench_latent_training(data: Path, ae_dir: Path, bf16: bool, steps: int, batch_size: int) -> dict:
    from tesseract4d.model.trainer import TrainConfig, Trainer

    with tempfile.TemporaryDirectory() as out:
        trainer = Trainer(TrainConfig(data=data, out=Path(out), preset="latent-128", autoencoder=ae_dir,
                                      precision="bf16" if bf16 else "fp32",
                                      max_steps=steps + 1, batch_size=batch_size, val_every=0, ckpt_every=0,
                                      quiet=True))
        trainer.train_step()
        _reset_peak_rss()
        s = median_seconds(trainer.train_step, steps)
        return {"s_per_step": s, "peak_mb": _peak_rss_mb()}


def bench_sampling_round_robin(entries: list[tuple[str, object, object]], steps: int, repeats: int) -> dict[str, float]:
    """Median seconds per clip of each (label, pipeline, first frame), timed in turns (one clip of
    each per round), so that the drift of a shared machine falls on every entry alike."""
    times: dict[str, list[float]] = {label: [] for label, _, _ in entries}
    for r in range(repeats):
        for label, pipe, first in entries:
            times[label].append(time_clip(pipe, first, steps, True, r))
    return {label: statistics.median(t) for label, t in times.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--autoencoder", type=Path, nargs="+", default=None,
                        help="trained autoencoder folder(s) (default: random weights); with several, the codec and "
                             "sampling rows are measured for each, training rows for the first")
    parser.add_argument("--autoencoder-preset", default="ae-f8c32", help="preset of the random autoencoder")
    parser.add_argument("--train-steps", type=int, default=5, help="timed training steps per row")
    parser.add_argument("--repeats", type=int, default=3, help="timed repeats per encode/decode/sampling row")
    parser.add_argument("--no-tiny", action="store_true", help="skip the pixel tiny rows")
    parser.add_argument("--no-training", action="store_true",
                        help="skip the training rows (codec and sampling rows only; more --repeats in the same time)")
    parser.add_argument("--guidance-min-sigma", type=float, nargs="*", default=[], metavar="S",
                        help="also time latent-128 (first autoencoder) guided only at noise >= S (a guidance "
                             "interval, as `set-sampler --guidance-min-sigma S` writes it), for each S given")
    add_isa_cap_argument(parser)
    args = parser.parse_args(argv)
    apply_isa_cap(args.cap_isa)

    from tesseract4d import runtime

    runtime.configure()
    import torch

    from tesseract4d.testing.synthetic_scene import write_segmented_dataset, write_synthetic_dataset

    from tesseract4d.model.autoencoder import RGBDNAutoencoder, get_autoencoder_preset, save_autoencoder
    from tesseract4d.precision import cpu_flags, has_fast_bf16

    print(machine_line())
    precisions = [False, True] if has_fast_bf16(cpu_flags()) else [False]
    rows = []

    def add(*row):
        rows.append(row)
        print(*row, sep=" | ", flush=True)

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        ae_dirs = args.autoencoder
        ae_preset = args.autoencoder_preset
        if not ae_dirs:
            torch.manual_seed(0)
            ae_dirs = [save_autoencoder(RGBDNAutoencoder(get_autoencoder_preset(ae_preset)), tmp / "ae")]
        data = None if args.no_training else write_segmented_dataset(tmp / "data128", episodes=4, frames=16, size=128)
        pixel = None if args.no_tiny else write_synthetic_dataset(tmp / "data64", episodes=4, frames=16, size=64)
        for bf16 in precisions:
            p = "bf16" if bf16 else "fp32"
            if not args.no_training:
                r = bench_autoencoder_training(data, ae_preset, bf16, args.train_steps)
                add(f"autoencoder {ae_preset}", p, "train b8 frames", f"{1 / r['s_per_step']:.2f} steps/s", f"{r['peak_mb']:.0f}")
                r = bench_latent_training(data, ae_dirs[0], bf16, args.train_steps, 4)
                add("latent-128", p, "train b4 (latent cache)", f"{1 / r['s_per_step']:.2f} steps/s", f"{r['peak_mb']:.0f}")
                if pixel is not None:
                    r = bench_training("tiny", pixel, bf16, args.train_steps, 4)
                    add("tiny", p, "train b4", f"{1 / r['s_per_step']:.2f} steps/s", f"{r['peak_mb']:.0f}")
            entries = []
            for i, ae_dir in enumerate(ae_dirs, 1):
                r = bench_autoencoder_codec(ae_dir, bf16, args.repeats)
                name = f"autoencoder {i} ({r['decoder']})" if len(ae_dirs) > 1 else f"autoencoder ({r['decoder']})"
                add(name, p, "encode 16-frame 128² clip", f"{r['encode_s']:.3f} s", f"{r['peak_mb']:.0f}")
                add(name, p, "decode 16-frame 128² clip", f"{r['decode_s']:.3f} s", f"{r['peak_mb']:.0f}")
                # Numbered when several are compared: two of the same depth must not share a row.
                label = f"latent-128, autoencoder {i} ({r['decoder']})" if len(ae_dirs) > 1 else "latent-128"
                entries.append((label, *sampling_pipeline("latent-128", bf16, autoencoder=ae_dir)))
            for sigma in args.guidance_min_sigma:
                pipe, first = sampling_pipeline("latent-128", bf16, autoencoder=ae_dirs[0])
                pipe.preset = dataclasses.replace(pipe.preset, guidance_min_sigma=sigma)
                entries.append((f"latent-128, guidance at noise >= {sigma:g}", pipe, first))
            if pixel is not None:
                entries.append(("tiny", *sampling_pipeline("tiny", bf16)))
            _reset_peak_rss()
            for label, s in bench_sampling_round_robin(entries, 10, args.repeats).items():
                add(label, p, "sample 10 steps, guidance 1.5 (in turns)", f"{s:.2f} s/clip", f"{_peak_rss_mb():.0f}")
    header = ("model", "precision", "what", "speed", "peak RSS MB")
    print()
    print_table(header, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
