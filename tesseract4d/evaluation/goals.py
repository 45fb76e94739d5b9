"""The project's held-out goals, read from `evaluate --heldout` reports, as one Markdown table.

`tesseract4d research goals` puts the models of one or more held-out reports (report.json, any format
since the contrast rows, version 5) side by side against the goals a world model here is held to:
on the moving region RGB PSNR ≥ 22 dB, depth AbsRel ≤ 0.15, normal error ≤ 20° and 4D Chamfer
≤ 20 mm; object permanence ≥ 95 %; instruction contrast and right-way following ≥ 70 %; no token
grid and edge sharpness ≥ 0.8. Every number is the report's own (its means over its episodes and
noise draws); nothing is measured again, so the table is regenerated exactly from the reports.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from tesseract4d.errors import UserError
from tesseract4d.evaluation.heldout import describe_sampler
from tesseract4d.evaluation.heldout_believability import (
    CONTRAST_GOAL, EDGE_SHARPNESS_GOAL, PRESENCE_GOAL, TOKEN_GRID_GOAL)
from tesseract4d.evaluation.instruction_following import RIGHT_WAY_COSINE

REPORT_FORMAT = "tesseract4d-heldout-eval"
MIN_FORMAT_VERSION = 5  # the first with the contrast's "found whole" count

# Moving-region goals of the reconstruction metrics (the believability goals live beside their measures).
PSNR_GOAL_DB = 22.0
ABS_REL_GOAL = 0.15
NORMAL_GOAL_DEG = 20.0
CHAMFER_GOAL_M = 0.020
RIGHT_WAY_GOAL = 0.70


@dataclass(frozen=True)
class Column:
    """One model of one report: ``method`` is its key in the report."""

    report: dict
    method: str
    label: str


@dataclass(frozen=True)
class Measure:
    """A row: its label (with the goal), how to read a column's cell, and whether the goal is met."""

    label: str
    cell: Callable[[Column], tuple[str, float | None]]  # (text, value the goal is judged on)
    met: Callable[[float], bool] | None = None


def load_report(folder: str | os.PathLike) -> dict:
    """report.json of an `evaluate --heldout` output folder (or the file itself), checked."""
    path = Path(folder)
    path = path / "report.json" if path.is_dir() else path
    if not path.is_file():
        raise UserError(f"{folder} holds no report.json; pass the --out folder of `tesseract4d evaluate --heldout`")
    try:
        report = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise UserError(f"{path} is not a readable report ({type(e).__name__}); run `evaluate --heldout` again") from e
    if not isinstance(report, dict) or report.get("format") != REPORT_FORMAT:
        raise UserError(f"{path} is not a held-out report (format {report.get('format') if isinstance(report, dict) else None!r}); "
                        f"pass the --out folder of `tesseract4d evaluate --heldout`")
    if int(report.get("format_version", 0)) < MIN_FORMAT_VERSION:
        raise UserError(f"{path} is report format {report.get('format_version')}; the goals need format "
                        f"{MIN_FORMAT_VERSION} or later: run `evaluate --heldout` again")
    return report


def columns(report: dict, set_label: str, references: bool = False) -> list[Column]:
    """The report's checkpoints (their predictions after the consistency step, as `demo` shows them),
    labelled by their folder names; with ``references`` also the autoencoder ceilings (one per distinct
    autoencoder among the checkpoints, named after the first checkpoint with it where there are several)
    and the static world."""
    cols = [Column(report, method, f"{set_label}: {Path(path).name}") for method, path in report["checkpoints"].items()]
    if references:
        ceilings = [(m, Path(p).name) for m, p in report["checkpoints"].items() if f"{m}_autoencoder" in report["summary"]]
        if "autoencoder" in report["summary"]:
            cols.append(Column(report, "autoencoder", f"{set_label}: ceiling (autoencoder)"))
        elif len(ceilings) == 1:
            cols.append(Column(report, f"{ceilings[0][0]}_autoencoder", f"{set_label}: ceiling (autoencoder)"))
        else:
            cols += [Column(report, f"{m}_autoencoder", f"{set_label}: ceiling ({name}'s autoencoder)") for m, name in ceilings]
        if "static" in report["summary"]:
            cols.append(Column(report, "static", f"{set_label}: static world"))
    return cols


def _finite(value) -> float | None:
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else None


def _summary(key: str, fmt: Callable[[float], str]) -> Callable[[Column], tuple[str, float | None]]:
    def cell(col: Column):
        value = _finite(col.report["summary"][col.method].get(key))
        return ("–" if value is None else fmt(value)), value
    return cell


def _count(right: str, total: str) -> Callable[[Column], tuple[str, float | None]]:
    """"right / total (share)" from the report's contrast entry of the column's method."""
    def cell(col: Column):
        entry = (col.report.get("contrast") or {}).get(col.method) or {}
        n = entry.get(total)
        if not n:
            return "–", None
        share = entry[right] / n
        return f"{entry[right]} / {n} ({share:.2f})", share
    return cell


def _right_way(col: Column) -> tuple[str, float | None]:
    follow = (col.report.get("instruction_following") or {}).get(col.method) or {}
    value = _finite(follow.get("right_way"))
    if value is None or not follow.get("episodes"):
        return "–", None
    return f"{value:.2f} of {follow['episodes']}", value


MEASURES = (
    Measure(f"RGB PSNR, moving (≥ {PSNR_GOAL_DB:g} dB)", _summary("rgb_psnr_db_moving", lambda v: f"{v:.2f}"),
            lambda v: v >= PSNR_GOAL_DB),
    Measure(f"depth AbsRel, moving (≤ {ABS_REL_GOAL:g})", _summary("depth_abs_rel_moving", lambda v: f"{v:.3f}"),
            lambda v: v <= ABS_REL_GOAL),
    Measure(f"normal error, moving (≤ {NORMAL_GOAL_DEG:g}°)", _summary("normal_mean_deg_moving", lambda v: f"{v:.1f}"),
            lambda v: v <= NORMAL_GOAL_DEG),
    Measure(f"4D Chamfer, moving (≤ {1000 * CHAMFER_GOAL_M:g} mm)",
            _summary("chamfer_l1_m_moving", lambda v: f"{1000 * v:.1f}"), lambda v: v <= CHAMFER_GOAL_M),
    Measure(f"object permanence (≥ {PRESENCE_GOAL:.0%})", _summary("objects_present", lambda v: f"{v:.3f}"),
            lambda v: v >= PRESENCE_GOAL),
    Measure(f"instruction contrast (≥ {CONTRAST_GOAL:.0%})", _count("right", "instructions"),
            lambda v: v >= CONTRAST_GOAL),
    Measure(f"moved the right way, cos > {RIGHT_WAY_COSINE:g} (≥ {RIGHT_WAY_GOAL:.0%})", _right_way,
            lambda v: v >= RIGHT_WAY_GOAL),
    Measure("contrast, the moved object found whole", _count("right_whole", "instructions")),
    Measure("\"keep still\" right", _count("still_right", "still_instructions")),
    Measure("active instructions right", _count("active_right", "active_instructions")),
    Measure("the arm goes to the instructed object", _count("arm_instructed", "arm_judged")),
    Measure(f"token grid ratio ({TOKEN_GRID_GOAL[0]:g}–{TOKEN_GRID_GOAL[1]:g})",
            _summary("token_grid_ratio", lambda v: f"{v:.3f}"), lambda v: TOKEN_GRID_GOAL[0] <= v <= TOKEN_GRID_GOAL[1]),
    Measure(f"edge sharpness (≥ {EDGE_SHARPNESS_GOAL:g})", _summary("edge_sharpness", lambda v: f"{v:.3f}"),
            lambda v: v >= EDGE_SHARPNESS_GOAL),
)


def goals_table(reports: list[tuple[str, dict]], references: bool = False) -> str:
    """The Markdown table of ``reports`` ((set label, report) pairs): a row per goal, a column per
    model of each report, ✓ where a goal is met and ✗ where not; then a line per report saying what
    it scored (episodes, noise draws, samplers)."""
    cols = [c for label, report in reports for c in columns(report, label, references)]
    lines = ["| measure (goal) | " + " | ".join(c.label for c in cols) + " |", "|" + "---|" * (1 + len(cols))]
    for m in MEASURES:
        cells = []
        for c in cols:
            text, value = m.cell(c)
            cells.append(text + ("" if m.met is None or value is None else " ✓" if m.met(value) else " ✗"))
        lines.append(f"| {m.label} | " + " | ".join(cells) + " |")
    lines.append("")
    for label, report in reports:
        seeds = report.get("sample_seeds") or [report.get("config", {}).get("sample_seed", 0)]
        sampler = report.get("sampler") or {}
        samplers = "; ".join(f"{Path(path).name} {describe_sampler(sampler[m])}"
                             for m, path in report["checkpoints"].items() if sampler.get(m))
        tracked = max((f.get("episodes", 0) for f in (report.get("instruction_following") or {}).values()), default=0)
        truth = (report.get("contrast") or {}).get("ground_truth") or {}
        arm = (f"; where the arm goes judged on the {truth['arm_judged']} of {truth['arm_measured']} active "
               f"instructions where the ground truth's own arm is found at the instructed object"
               if truth.get("arm_measured") else "")
        lines.append(f"- {label}: {report['episodes']} held-out episodes of {report.get('config', {}).get('data', '?')} "
                     f"({', '.join(report.get('tasks', []))}), noise seeds {', '.join(map(str, seeds))}"
                     + (f"; samplers: {samplers}" if samplers else "")
                     + f"; moved the right way over the {tracked} predictions whose instructed object the colour "
                       f"tracker follows{arm}.")
    return "\n".join(lines)


def parse_report_argument(text: str) -> tuple[str, Path]:
    """"FOLDER" or "FOLDER=LABEL" -> (label, folder); the label defaults to the folder's name."""
    folder, _, label = text.partition("=")
    if not folder:
        raise UserError(f"{text!r}: pass a report folder, optionally as FOLDER=LABEL")
    return (label or Path(folder).name), Path(folder)


__all__ = ["MEASURES", "columns", "goals_table", "load_report", "parse_report_argument"]
