"""The instruction timeline of a chained scene: which segment's words the shown frame belongs to.

A chained episode (datagen `--set chain_skills=N`) and its prediction carry an instruction schedule
(tesseract4d/instruction_schedule.py), kept by the reconstruction in ``metadata["instruction_schedule"]``.
The viewer's Playback panel lists the segments with their frames and marks the one the shown frame
belongs to.
"""

from __future__ import annotations

from tesseract4d.instruction_schedule import Segment, schedule_of, segment_at


def scene_schedule(metadata: dict) -> list[Segment] | None:
    """The schedule of a reconstruction's metadata, or None for a one-instruction scene."""
    return schedule_of(metadata)


def timeline_markdown(segments: list[Segment], frame: int, num_frames: int) -> str:
    """Markdown lines ``k. words (frames a–b)``, the segment holding ``frame`` in bold with a marker."""
    now = segment_at(segments, frame)
    lines = []
    for i, s in enumerate(segments):
        end = s.frame_end if s.frame_end is not None else num_frames - 1
        text = f"{i + 1}. {s.instruction} (frames {s.frame_start}–{end})"
        lines.append(f"▶ **{text}**" if i == now else text)
    return "  \n".join(lines)
