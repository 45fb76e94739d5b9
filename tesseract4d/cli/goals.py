"""Print the project's held-out goals against one or more `evaluate --heldout` reports, as a Markdown table.

One column per checkpoint of each report (its predictions as `demo` shows them), one row per goal:
moving-region RGB PSNR, depth AbsRel, normal error and 4D Chamfer; object permanence; instruction
contrast, right-way following, the moved object found whole, "keep still"; token grid and edge
sharpness; ✓ where a goal is met, ✗ where not. Numbers are read from the reports, not measured
again, so the same reports always give the same table (docs/evaluation.md's is made this way); redirect it
into a file to keep it (`... > goals.md`).

Example:
  tesseract4d evaluate --heldout data/heldout_groups128 --checkpoint tesseract4d/checkpoints/v2 \\
      --checkpoint tesseract4d/checkpoints/v2-2step --sample-seed 0 1 --out outputs/tabletop
  tesseract4d evaluate --heldout data/heldout_cubegroups128 --max-per-task 8 --checkpoint tesseract4d/checkpoints/v2 \\
      --checkpoint tesseract4d/checkpoints/v2-2step --sample-seed 0 1 --out outputs/cubes
  tesseract4d research goals outputs/tabletop=tabletop outputs/cubes="cube tasks" --references
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("reports", nargs="+", metavar="FOLDER[=LABEL]",
                        help="--out folders of `evaluate --heldout` (or their report.json), each optionally labelled "
                             "(default label: the folder's name)")
    parser.add_argument("--references", action="store_true",
                        help="add each report's autoencoder ceiling and static world columns")


def run(args: argparse.Namespace) -> int:
    from tesseract4d.evaluation.goals import goals_table, load_report, parse_report_argument

    reports = [(label, load_report(folder)) for label, folder in map(parse_report_argument, args.reports)]
    table = goals_table(reports, references=args.references)
    print(table)
    return 0
