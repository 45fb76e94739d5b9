"""Instruction schedules: parsing, segment boundaries, and which words each clip of a rollout gets."""

from __future__ import annotations

import pytest

from tesseract4d.errors import UserError
from tesseract4d.instruction_schedule import (
    Segment, chained_instruction, clip_instructions, clip_new_frames, parse_schedule, schedule_of, segment_at,
    segment_boundaries,
)


def test_clips_cover_every_frame_once_and_match_the_pipeline_count():
    for num_frames, clip_len in [(16, 16), (64, 16), (17, 16), (22, 8), (5, 8), (1, 16)]:
        clips = clip_new_frames(num_frames, clip_len)
        frames = [f for c in clips for f in c]
        assert frames == list(range(1, num_frames))
        # the count the autoregressive rollout always had: one clip, then one per clip_len - 1 new frames
        expected = 1 if num_frames <= clip_len else 1 + -(-(num_frames - clip_len) // (clip_len - 1))
        assert len(clips) == expected
    assert [list(c)[:1] for c in clip_new_frames(64, 16)] == [[1], [16], [31], [46], [61]]


def test_boundaries_are_even_and_shared():
    assert segment_boundaries(64, 4) == [0, 16, 32, 47, 63]
    assert segment_boundaries(9, 3) == [0, 3, 5, 8]
    with pytest.raises(UserError, match="at least 4 frames"):
        segment_boundaries(3, 3)


def test_parse_and_refuse():
    segs = parse_schedule("0:push the red cube left; 30:lift the blue cylinder")
    assert [(s.instruction, s.frame_start, s.frame_end) for s in segs] == [
        ("push the red cube left", 0, 30), ("lift the blue cylinder", 30, None)]
    for bad, words in [("5:push", "frame 0"), ("0:a;0:b", "increase"), ("push the cube", "FRAME:WORDS"), ("0: ", "no words")]:
        with pytest.raises(UserError, match=words):
            parse_schedule(bad)


def test_each_clip_gets_the_segment_holding_most_of_its_new_frames():
    segs = [Segment("a", 0, 16), Segment("b", 16, 32), Segment("c", 32, 47), Segment("d", 47, 63)]
    assert segment_at(segs, 0) == 0 and segment_at(segs, 16) == 0 and segment_at(segs, 17) == 1
    # clips of 64 frames add 1-15, 16-30, 31-45, 46-60, 61-63
    assert clip_instructions(segs, 64, 16) == ["a", "b", "c", "d", "d"]
    # a clip split 3 / 4 between two segments goes to the one with 4
    assert clip_instructions(parse_schedule("0:a;10:b"), 22, 8) == ["a", "b", "b"]
    # a one-clip rollout is given the first segment's words
    assert clip_instructions(parse_schedule("0:a;30:b"), 16, 16) == ["a"]


def test_schedule_round_trips_through_metadata():
    segs = [Segment("push it", 0, 5, {"skill": "push"}, 0, 80), Segment("lift it", 5, 9, {"skill": "lift"}, 80, 170)]
    assert schedule_of({"instruction_schedule": [s.to_dict() for s in segs]}) == segs
    assert schedule_of({}) is None
    assert chained_instruction(["push it ", "lift it"]) == "push it, then lift it"
