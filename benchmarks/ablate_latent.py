"""Recipe-lever ablation of the latent world model at a fixed training budget.

Every trained variant starts from scratch on the same data, seed and number of minutes, and
differs from the baseline (the recipe v2 ships: first-frame noise 0.1, moving and object weight 2,
clean-sample target, text dropout 0.1, ``latent-128``) in one lever only. The guidance variants
reuse the baseline's weights and change only the sampler's text guidance scale. ``seed_1`` repeats
the baseline with another training seed: how far two runs of one recipe differ is the yardstick
for every other row.

Each variant is scored by the held-out evaluation (``tesseract4d evaluate --heldout``) on the
same episodes: moving-region RGB PSNR, depth AbsRel, normal error and 4D Chamfer of the raw
prediction, object permanence, instruction contrast over counterfactual groups and whether
"keep still" stays still, with the static world's value beside the first row. Runs go to
OUT/<variant>/ and are resumed when present: a finished variant is neither retrained nor
re-evaluated, so the command can be run again after an interruption. The table is printed and
written to OUT/ablation.md (and OUT/ablation.json).

  .venv/bin/python benchmarks/ablate_latent.py --data data/v2_tabletop data/v2_tasks data/ae128 \\
      --autoencoder tesseract4d/checkpoints/v2/autoencoder --heldout data/heldout_groups128 --max-per-task 16 \\
      --out runs/ablation --minutes 9 [--variants baseline,seed_1]

(The README's table was made with v2's autoencoder before its decoder fine-tune, runs/v2/ae_ft: the
same encoder, so the same latents, and an older decoder.)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

BASELINE = ["--preset", "latent-128", "--condition-noise", "0.1", "--moving-weight", "2", "--object-weight", "2",
            "--text-dropout", "0.1"]

# variant -> (what changes, `tesseract4d train` arguments replacing the baseline's, or None to reuse the
# baseline's weights, extra `tesseract4d evaluate` arguments)
VARIANTS: dict[str, tuple[str, list[str] | None, list[str]]] = {
    "baseline": ("v2 recipe", [], []),
    "seed_1": ("v2 recipe, training seed 1 (run-to-run spread)", ["--seed", "1"], []),
    "cond_noise_0": ("no first-frame noise", ["--condition-noise", "0"], []),
    "weights_1": ("moving and object weight 1", ["--moving-weight", "1", "--object-weight", "1"], []),
    "text_dropout_0.3": ("text dropout 0.3", ["--text-dropout", "0.3"], []),
    "time_logit_normal_1": ("diffusion times logit-normal (1), most at middle noise", ["--time-logit-normal", "1"], []),
    "group_batches": ("batches of whole counterfactual groups, one noise and time each", ["--group-batches"], []),
    "counterfactual_swap_0.5": ("group batches, counterfactual swap 0.5",
                                ["--group-batches", "--counterfactual-swap", "0.5"], []),
    "text_noise_0.5": ("noise on the instruction's token embeddings (0.5 of their size at most)",
                       ["--text-noise", "0.5"], []),
    "guidance_1": ("text guidance 1 (none)", None, ["--text-guidance", "1"]),
    "guidance_3": ("text guidance 3", None, ["--text-guidance", "3"]),
}
COLUMNS = (("rgb_psnr_db_moving", "PSNR moving (dB)", ".2f"), ("depth_abs_rel_moving", "AbsRel moving", ".3f"),
           ("normal_mean_deg_moving", "normals moving (°)", ".1f"), ("chamfer_l1_m_moving", "Chamfer moving (mm)", ".1f"),
           ("objects_present", "objects present", ".3f"), ("contrast", "contrast", ".3f"),
           ("contrast_whole", "contrast, found whole", ".3f"))


def train_args(extra: list[str]) -> list[str]:
    """The baseline's arguments with the flags in ``extra`` replaced by theirs (a flag not followed by
    a value, such as ``--group-batches``, is a switch and is added)."""
    args, i = list(BASELINE), 0
    while i < len(extra):
        flag = extra[i]
        if i + 1 == len(extra) or extra[i + 1].startswith("--"):
            args += [] if flag in args else [flag]
            i += 1
            continue
        value = extra[i + 1]
        if flag in args:
            args[args.index(flag) + 1] = value
        else:
            args += [flag, value]
        i += 2
    return args


def keep_still(report: dict, method: str) -> str:
    """'right/total' over the keep-still instructions of the report's counterfactual groups."""
    total = report["episodes_per_skill"].get("keep_still", 0)
    share = report["contrast"][method].get("per_skill", {}).get("keep_still", 0.0)
    return f"{round(share * total)}/{total}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, nargs="+", required=True, help="training dataset folder(s)")
    parser.add_argument("--heldout", type=Path, required=True, help="held-out counterfactual groups")
    parser.add_argument("--autoencoder", type=Path, required=True, help="exported RGB-D-N autoencoder (all variants)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--minutes", type=float, default=9.0, help="training budget per variant (default %(default)s)")
    parser.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated (default: all)")
    parser.add_argument("--precision", choices=("auto", "fp32", "bf16"), default="auto",
                        help="passed to every run (default %(default)s: bf16 only where the CPU has it)")
    parser.add_argument("--max-per-task", type=int, default=16,
                        help="held-out episodes per task; whole groups of the counterfactual set (default %(default)s)")
    args = parser.parse_args(argv)
    names = args.variants.split(",")
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        parser.error(f"unknown variant(s) {', '.join(unknown)}; choose from {', '.join(VARIANTS)}")
    cli = [sys.executable, "-m", "tesseract4d.cli"]
    results = {}
    for name in names:
        label, extra, eval_extra = VARIANTS[name]
        run = args.out / ("baseline" if extra is None else name)
        if not (run / "final" / "tesseract4d_config.json").is_file():
            if extra is None:
                raise SystemExit(f"{name} samples the baseline's weights: run the 'baseline' variant first")
            cmd = [*cli, "train", "--data", *map(str, args.data), "--autoencoder", str(args.autoencoder),
                   "--out", str(run), "--max-minutes", str(args.minutes), "--max-steps", "100000", "--val-every", "0",
                   "--no-progress", "--precision", args.precision, *train_args(extra)]
            resume = ["--resume"] if (run / "train_config.json").is_file() else []
            subprocess.run(cmd + resume, check=True)
        eval_dir = args.out / name / "eval"
        report_path = eval_dir / "report.json"
        if not report_path.is_file():
            subprocess.run([*cli, "evaluate", "--checkpoint", str(run / "final"), "--heldout", str(args.heldout),
                            "--out", str(eval_dir), "--max-per-task", str(args.max_per_task), "--precision",
                            args.precision, *eval_extra], check=True, stdout=subprocess.DEVNULL)
        report = json.loads(report_path.read_text())
        config = json.loads((run / "final" / "tesseract4d_config.json").read_text())
        model = next(k for k in report["summary"] if k.endswith("_raw"))
        results[name] = {"label": label, "steps": config["training"]["steps"], "model": report["summary"][model],
                         "static": report["summary"]["static"], "keep_still": keep_still(report, model),
                         "static_keep_still": keep_still(report, "static"),
                         "episodes": sum(report["episodes_per_task"].values())}
        print(name, json.dumps({k: v for k, v in results[name].items() if k not in ("model", "static")}), flush=True)
    table = format_table(results, args)
    print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ablation.md").write_text(table + "\n")
    (args.out / "ablation.json").write_text(json.dumps(results, indent=1) + "\n")
    return 0


def format_table(results: dict, args: argparse.Namespace) -> str:
    header = ("variant", "what changes", "steps", *(label for _, label, _ in COLUMNS), "keep still")
    lines = [f"{args.minutes:g} min of training per variant; held-out {args.heldout} "
             f"({next(iter(results.values()))['episodes']} episodes); raw prediction, moving region", "",
             "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    first = next(iter(results.values()))
    for name, r in results.items():
        cells = [f"{r['model'][k]:{fmt}}" if k != "chamfer_l1_m_moving" else f"{1000 * r['model'][k]:{fmt}}"
                 for k, _, fmt in COLUMNS]
        lines.append("| " + " | ".join((name, r["label"], str(r["steps"]), *cells, r["keep_still"])) + " |")
    static = [f"{first['static'][k]:{fmt}}" if k != "chamfer_l1_m_moving" else f"{1000 * first['static'][k]:{fmt}}"
              for k, _, fmt in COLUMNS]
    lines.append("| " + " | ".join(("static world", "first frame repeated", "-", *static, first["static_keep_still"])) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
