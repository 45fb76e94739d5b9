"""Inspect or validate a dataset folder.

  tesseract4d dataset info DIR    episodes, tasks, frames, resolution, size on disk, success;
                                  for skill data also groups and per-skill counts and planner rates
  tesseract4d dataset check DIR   reads every episode shard completely with the reader and checks
                                  its content (depth >= 0, unit normals, K, rigid poses, named
                                  segmentation ids); lists the bad ones and exits non-zero if any
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

from tesseract4d.dataset_format import (
    DatasetFormatError, list_episode_files, read_episode, read_episode_attrs, read_info,
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True)
    info = sub.add_parser("info", help="summary of a dataset folder")
    info.add_argument("dir", type=Path, help="dataset folder written by `tesseract4d datagen` (or predict)")
    info.add_argument("--json", action="store_true", help="print the summary as JSON")
    check = sub.add_parser("check", help="validate every episode shard")
    check.add_argument("dir", type=Path, help="dataset folder whose episode files are read one by one")


def _size_bytes(root: Path) -> int:
    return sum(p.stat().st_size for p in root.rglob("*") if p.is_file())


def _human(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"


def dataset_summary(root: Path) -> dict:
    """Counts per task from episode attributes (cheap: no frames are read)."""
    info = read_info(root)
    tasks: dict[str, dict] = defaultdict(lambda: {"episodes": 0, "frames": 0, "successful": 0})
    skills: dict[str, dict] = defaultdict(lambda: {"episodes": 0, "frames": 0, "intent_met": 0})
    groups: set[str] = set()
    unreadable = []
    for path in list_episode_files(root):
        try:
            a = read_episode_attrs(path)
        except DatasetFormatError:
            unreadable.append(str(path))
            continue
        t = tasks[a["env_id"]]
        t["episodes"] += 1
        t["frames"] += a["num_frames"]
        t["successful"] += int(a["success"] == 1)
        if a["intent"]:
            s = skills[a["intent"]["variant"]]
            s["episodes"] += 1
            s["frames"] += a["num_frames"]
            s["intent_met"] += int(bool(a["intent"].get("success")))
        if a["variant"] is not None:
            groups.add(a["group_id"])
    report_path = root / "datagen_report.json"
    rates, skill_rates = {}, {}
    if report_path.is_file():
        try:
            report = json.loads(report_path.read_text())
            rates = {k: v.get("success_rate") for k, v in report["tasks"].items()}
            skill_rates = {k: v.get("success_rate") for k, v in report.get("skills", {}).items()}
        except (json.JSONDecodeError, KeyError):
            rates = {}
    return {
        "path": str(root),
        "format_version": info.format_version,
        "resolution": f"{info.height}x{info.width}",
        "cameras": info.cameras,
        "episodes": sum(t["episodes"] for t in tasks.values()),
        "frames": sum(t["frames"] for t in tasks.values()),
        "size_bytes": _size_bytes(root),
        "tasks": {k: dict(v, planner_success_rate=rates.get(k)) for k, v in sorted(tasks.items())},
        "groups": len(groups),
        "skills": {k: dict(v, planner_success_rate=skill_rates.get(k)) for k, v in sorted(skills.items())},
        "unreadable": unreadable,
    }


def _info(root: Path, as_json: bool) -> int:
    s = dataset_summary(root)
    if as_json:
        print(json.dumps(s, indent=2))
        return 0
    print(f"dataset   {s['path']}  (format v{s['format_version']}, {s['resolution']}, cameras {', '.join(s['cameras'])})")
    print(f"episodes  {s['episodes']}   frames {s['frames']}   size {_human(s['size_bytes'])}")
    print(f"{'task':<22} {'episodes':>8} {'frames':>8} {'success':>8} {'planner rate':>13}")
    for env_id, t in s["tasks"].items():
        rate = "-" if t["planner_success_rate"] is None else f"{100 * t['planner_success_rate']:.0f} %"
        print(f"{env_id:<22} {t['episodes']:>8} {t['frames']:>8} {t['successful']:>8} {rate:>13}")
    if s["skills"]:
        print(f"counterfactual groups {s['groups']}")
        print(f"{'skill':<22} {'episodes':>8} {'frames':>8} {'met':>8} {'planner rate':>13}")
        for name, t in s["skills"].items():
            rate = "-" if t["planner_success_rate"] is None else f"{100 * t['planner_success_rate']:.0f} %"
            print(f"{name:<22} {t['episodes']:>8} {t['frames']:>8} {t['intent_met']:>8} {rate:>13}")
    if s["unreadable"]:
        print(f"{len(s['unreadable'])} unreadable episode file(s); run `tesseract4d dataset check {root}`")
    return 0


def _check(root: Path) -> int:
    info = read_info(root)
    files = list_episode_files(root)
    bad = []
    for path in files:
        try:
            episode = read_episode(path)
            episode.check_content()
            if path.relative_to(root).as_posix() != f"episodes/{episode.episode_id}.h5":
                raise DatasetFormatError(f"holds episode {episode.episode_id}, which belongs elsewhere")
            if episode.source != info.source:
                raise DatasetFormatError(f"holds a {episode.source} episode in a {info.source} dataset")
        except DatasetFormatError as e:
            bad.append((path, str(e)))
    for path, msg in bad:
        print(f"BAD  {path}: {msg}")
    print(f"checked {len(files)} episode file(s): {len(files) - len(bad)} ok, {len(bad)} bad")
    if bad:
        print("Delete the bad files and rerun the same `tesseract4d datagen` command to regenerate them (their seeds are simulated again).")
        return 1
    return 0


def run(args: argparse.Namespace) -> int:
    if args.action == "info":
        return _info(args.dir, args.json)
    return _check(args.dir)
