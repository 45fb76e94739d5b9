"""Instruction schedules: which words hold for which frames of a long episode.

A chained episode (``datagen/chains.py``: "push the red cube left, then lift the blue cylinder") is
a sequence of *segments*, each with its own instruction, structured intent and frame range. Frame
ranges share their boundary frame: segment i runs from ``frame_start`` to ``frame_end`` (both
included) and segment i + 1 starts at segment i's ``frame_end``. The schedule is stored in an
episode's ``metadata[SCHEDULE_KEY]`` as a list of :meth:`Segment.to_dict` dicts.

Prediction reads the schedule clip by clip (``model/pipeline.py``): a rollout longer than one clip
is sampled as clips whose new frames are :func:`clip_new_frames`, and each clip is given the
instruction of the segment that holds most of its new frames (:func:`clip_instructions`), so a
segment's words reach the model when its clip starts.

A user writes a schedule as text (``predict --set schedule=...``): ``FRAME:WORDS`` entries joined by
``;``, starting frames in increasing order from 0, e.g. ``0:push the red cube left;30:lift the blue
cylinder``; each segment ends where the next starts, the last at the rollout's end.
"""

from __future__ import annotations

from dataclasses import dataclass

from tesseract4d.errors import UserError

SCHEDULE_KEY = "instruction_schedule"
THEN = ", then "  # joins the segments' words into the episode's one instruction


@dataclass(frozen=True)
class Segment:
    """One instruction of a schedule: its words, first and last frame (inclusive; the boundary
    frame is shared with the neighbouring segment) and, for simulated episodes, its structured
    intent (datagen/skills.py) and simulator step range."""

    instruction: str
    frame_start: int
    frame_end: int | None = None  # None: until the end of the rollout
    intent: dict | None = None
    step_start: int | None = None
    step_end: int | None = None

    def to_dict(self) -> dict:
        return {"instruction": self.instruction, "frame_start": self.frame_start, "frame_end": self.frame_end,
                "intent": self.intent, "step_start": self.step_start, "step_end": self.step_end}

    @classmethod
    def from_dict(cls, d: dict) -> "Segment":
        return cls(instruction=str(d["instruction"]), frame_start=int(d["frame_start"]),
                   frame_end=None if d.get("frame_end") is None else int(d["frame_end"]), intent=d.get("intent"),
                   step_start=d.get("step_start"), step_end=d.get("step_end"))


def chained_instruction(texts: list[str]) -> str:
    """The one instruction of a chained episode: its segments' words joined by ", then "."""
    return THEN.join(t.strip() for t in texts)


def segment_boundaries(num_frames: int, num_segments: int) -> list[int]:
    """The frames where ``num_segments`` segments of a ``num_frames``-frame episode start and end,
    spread evenly: ``num_segments + 1`` strictly increasing frames from 0 to ``num_frames - 1``."""
    if num_segments < 1 or num_frames - 1 < num_segments:
        raise UserError(f"{num_frames} frames cannot hold {num_segments} segments of at least 2 frames each; "
                        f"keep at least {num_segments + 1} frames (--frames)")
    return [round(i * (num_frames - 1) / num_segments) for i in range(num_segments + 1)]


def schedule_of(metadata: dict) -> list[Segment] | None:
    """The schedule stored in an episode's metadata, or None for a one-instruction episode."""
    raw = (metadata or {}).get(SCHEDULE_KEY)
    return None if not raw else [Segment.from_dict(d) for d in raw]


def check_schedule(segments: list[Segment]) -> None:
    """Refuse a schedule that does not start at frame 0 or whose starts do not increase."""
    if not segments:
        raise UserError("the instruction schedule is empty; give at least one FRAME:WORDS entry")
    if segments[0].frame_start != 0:
        raise UserError(f"the instruction schedule starts at frame {segments[0].frame_start}; its first entry must "
                        f"start at frame 0, e.g. '0:push the red cube left;30:lift the blue cylinder'")
    starts = [s.frame_start for s in segments]
    if any(b <= a for a, b in zip(starts, starts[1:])):
        raise UserError(f"the instruction schedule's starting frames {starts} must increase")
    for s in segments:
        if not s.instruction.strip():
            raise UserError(f"the instruction schedule has no words at frame {s.frame_start}; say what should happen")


def parse_schedule(text: str) -> list[Segment]:
    """``'0:push the red cube left;30:lift the blue cylinder'`` -> segments (see the module docstring)."""
    segments = []
    entries = [e for e in text.split(";") if e.strip()]
    for entry in entries:
        frame, sep, words = entry.partition(":")
        if not sep or not frame.strip().isdigit():
            raise UserError(f"instruction schedule entry {entry.strip()!r} is not FRAME:WORDS; write e.g. "
                            f"'0:push the red cube left;30:lift the blue cylinder'")
        segments.append(Segment(words.strip(), int(frame)))
    check_schedule(segments)
    ends = [s.frame_start for s in segments[1:]] + [None]
    return [Segment(s.instruction, s.frame_start, end) for s, end in zip(segments, ends)]


def clip_new_frames(num_frames: int, clip_len: int, history: int = 1) -> list[range]:
    """The frames each clip of a ``num_frames`` rollout adds: clip 0 frames 1 .. clip_len - 1 (frame
    0 is given), clip k > 0 the ``clip_len - history`` frames after its first ``history`` frames, which
    are the last ``history`` frames of the rollout so far (1: the last frame of clip k - 1). The last
    clip is cut at ``num_frames``."""
    if clip_len < 2:
        return [range(1, num_frames)] if num_frames > 1 else [range(1, 1)]
    if not 1 <= history < clip_len:
        raise ValueError(f"history must be 1 .. {clip_len - 1} frames for clips of {clip_len}, got {history}")
    out = [range(1, min(clip_len, num_frames))]
    start = clip_len - 1
    while start < num_frames - 1:
        out.append(range(start + 1, min(start + 1 + clip_len - history, num_frames)))
        start += clip_len - history
    return out


def segment_at(segments: list[Segment], frame: int) -> int:
    """Index of the segment that frame ``frame`` belongs to: a boundary frame belongs to the segment
    it ends (frame 0 to the first)."""
    index = 0
    for i, s in enumerate(segments):
        if frame > s.frame_start:
            index = i
    return index


def clip_instructions(segments: list[Segment], num_frames: int, clip_len: int, history: int = 1) -> list[str]:
    """The instruction given to each clip of a ``num_frames`` rollout (clips continuing from ``history``
    frames, :func:`clip_new_frames`): the segment holding most of the clip's new frames (a tie goes to
    the later segment, whose words the clip starts to act on)."""
    check_schedule(segments)
    out = []
    for frames in clip_new_frames(num_frames, clip_len, history):
        counts: dict[int, int] = {}
        for f in frames:
            i = segment_at(segments, f)
            counts[i] = counts.get(i, 0) + 1
        best = max(counts, key=lambda i: (counts[i], i)) if counts else 0
        out.append(segments[best].instruction)
    return out
