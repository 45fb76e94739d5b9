"""Recipe-lever ablation of the latent world model at a fixed training budget.

Each variant trains ``latent-128`` (or a width/depth variant of it) from scratch for the same
number of minutes on the same data and seed, then is scored by the held-out evaluation
(``tesseract4d evaluate --checkpoint --heldout``): moving-region metrics of the raw prediction and
instruction following (share of clips moving the target the right way, mean direction cosine).
Runs go to OUT/<variant>/ (resumed when present: a finished variant is not retrained).

  .venv/bin/python benchmarks/ablate_latent.py --data data/ae128 --heldout data/ae128_heldout \\
      --autoencoder runs/ae/autoencoder --out runs/ablation --minutes 30 [--variants baseline,cond_noise]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

# variant -> extra `tesseract4d train` arguments
VARIANTS: dict[str, list[str]] = {
    "baseline": [],
    "cond_noise_0.3": ["--condition-noise", "0.3"],
    "moving_weight_4": ["--moving-weight", "4"],
    "object_weight_4": ["--object-weight", "4"],
    "velocity": ["--prediction", "velocity"],
    "text_dropout_0.3": ["--text-dropout", "0.3"],
    "small_2_layers": ["--preset", "latent-128-small"],
    "large_8_layers": ["--preset", "latent-128-large"],
}
COLUMNS = (("rgb_psnr_db_moving", "RGB PSNR moving (dB)"), ("depth_abs_rel_moving", "depth AbsRel moving"),
           ("normal_mean_deg_moving", "normal err moving (°)"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--heldout", type=Path, required=True)
    parser.add_argument("--autoencoder", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--minutes", type=float, default=30.0, help="training budget per variant (default %(default)s)")
    parser.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated (default: all)")
    parser.add_argument("--precision", choices=("auto", "fp32", "bf16"), default="auto",
                        help="passed to every training run (default %(default)s: bf16 only where the CPU has it)")
    parser.add_argument("--max-per-task", type=int, default=3)
    args = parser.parse_args(argv)
    cli = [sys.executable, "-m", "tesseract4d.cli"]
    rows = []
    for name in args.variants.split(","):
        run = args.out / name
        extra = VARIANTS[name]
        if not (run / "final" / "tesseract4d_config.json").is_file():
            cmd = [*cli, "train", "--data", str(args.data), "--autoencoder", str(args.autoencoder), "--out", str(run),
                   "--max-minutes", str(args.minutes), "--max-steps", "100000", "--val-every", "0", "--no-progress",
                   "--precision", args.precision, *extra]
            subprocess.run(cmd, check=True)
        report_path = run / "eval" / "report.json"
        if not report_path.is_file():
            subprocess.run([*cli, "evaluate", "--checkpoint", str(run / "final"), "--heldout", str(args.heldout),
                            "--out", str(run / "eval"), "--max-per-task", str(args.max_per_task)], check=True)
        report = json.loads(report_path.read_text())
        steps = json.loads((run / "final" / "tesseract4d_config.json").read_text())["training"]["steps"]
        model, static = report["summary"]["model_raw"], report["summary"]["static"]
        follow = report["instruction_following"]["model_raw"]
        rows.append((name, str(steps), *(f"{model[k]:.3g} ({static[k]:.3g})" for k, _ in COLUMNS),
                     f"{follow.get('right_way', float('nan')):.2f}", f"{follow.get('mean_cosine', float('nan')):.2f}"))
        print(*rows[-1], sep=" | ", flush=True)
    header = ("variant", "steps", *(label + " (static)" for _, label in COLUMNS), "right way", "cosine")
    print(f"\n{args.minutes:g} min per variant; held-out {args.heldout}; the static world in brackets\n")
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for row in rows:
        print("| " + " | ".join(row) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
