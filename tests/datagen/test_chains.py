"""Chained episodes: skills in a row in one tabletop scene, each segment with its words, intent and frames."""

from __future__ import annotations

import numpy as np
import pytest

from datagen.chains import chain_frames, check_chain
from datagen.tabletop import ENV_ID as TABLETOP
from tesseract4d.cli import main
from tesseract4d.dataset_format import list_episode_files, read_episode
from tesseract4d.errors import UserError
from tesseract4d.instruction_schedule import THEN, schedule_of

CHAIN_SEED, CHAIN_FRAMES, CHAIN_SIZE = 0, 7, 32


def test_each_segment_keeps_its_share_of_frames_at_its_own_pace():
    keep, bounds = chain_frames([0, 40, 200], 7)  # a short first skill, a long second one
    assert bounds == [0, 3, 6]
    assert list(keep[:4]) == [0, 13, 27, 40] and keep[3] == 40 and keep[-1] == 200  # the boundary is a shared frame
    assert len(keep) == 7 and np.all(np.diff(keep) > 0)
    keep, bounds = chain_frames([0, 3, 5], 0)  # every state
    assert list(keep) == [0, 1, 2, 3, 4, 5] and bounds == [0, 3, 5]
    with pytest.raises(UserError, match="keep fewer --frames"):
        chain_frames([0, 2, 100], 9)  # 3 states cannot give 5 frames


@pytest.mark.parametrize("args, words", [
    ((1, [TABLETOP], 16, None), "2 to 4"), ((5, [TABLETOP], 64, None), "2 to 4"),
    ((2, ["PickCube-v1"], 16, None), "tabletop scene only"), ((4, [TABLETOP], 4, None), "at least 5 frames"),
    ((3, [TABLETOP], 16, ["push_left", "lift"]), "3 distinct skills"),
])
def test_refusals_say_the_fix(args, words):
    with pytest.raises(UserError, match=words):
        check_chain(*args)


def _datagen(out, capsys):
    argv = ["datagen", "--tasks", TABLETOP, "--episodes", "1", "--seed-start", str(CHAIN_SEED), "--resolution",
            str(CHAIN_SIZE), "--frames", str(CHAIN_FRAMES), "--set", "chain_skills=2", "--set", "previews=false",
            "--out", str(out), "--quiet"]
    assert main(argv) == 0
    return capsys.readouterr().out


@pytest.fixture(scope="module")
def chained(tmp_path_factory):
    out = tmp_path_factory.mktemp("chains") / "ds"
    assert main(["datagen", "--tasks", TABLETOP, "--episodes", "1", "--seed-start", str(CHAIN_SEED), "--resolution",
                 str(CHAIN_SIZE), "--frames", str(CHAIN_FRAMES), "--set", "chain_skills=2", "--set", "previews=false",
                 "--out", str(out), "--quiet"]) == 0
    return out


@pytest.mark.sim
def test_the_schedule_is_stored_with_each_segments_frames_and_intent(chained):
    (path,) = list_episode_files(chained)
    assert path.name == f"seed_{CHAIN_SEED:06d}.h5"
    ep = read_episode(path)
    schedule = schedule_of(ep.metadata)
    assert len(schedule) == 2 and ep.num_frames == CHAIN_FRAMES
    assert ep.instruction == THEN.join(s.instruction for s in schedule)
    assert [(s.frame_start, s.frame_end) for s in schedule] == [(0, 3), (3, 6)]
    assert schedule[0].step_start == 0 and schedule[0].step_end == schedule[1].step_start
    assert schedule[1].step_end == len(ep.actions)
    assert schedule[0].intent["variant"] != schedule[1].intent["variant"]
    for seg in schedule:
        assert seg.intent["success"] and seg.instruction
        # the stored frames at a segment's ends are the simulator states at its ends
        assert ep.frame_steps[seg.frame_start] == seg.step_start and ep.frame_steps[seg.frame_end] == seg.step_end
        target = seg.intent["target"]
        if target is not None:  # the target's recorded move over the segment's frames is the judged one
            moved = ep.object_poses[target][seg.frame_end, :3] - ep.object_poses[target][seg.frame_start, :3]
            np.testing.assert_allclose(moved, seg.intent["achieved_displacement_world_m"], atol=1e-5)


@pytest.mark.sim
def test_a_rerun_resumes_and_a_fresh_simulator_makes_the_same_episode(chained, capsys):
    from datagen.chains import run_chain
    from datagen.simulate import EpisodeSimulator, SimConfig

    (path,) = list_episode_files(chained)
    before = path.stat().st_mtime_ns
    printed = _datagen(chained, capsys)
    assert "this run: 0 episodes from 0 attempts" in printed and path.stat().st_mtime_ns == before
    ep = read_episode(path)
    sim = EpisodeSimulator(TABLETOP, SimConfig(height=CHAIN_SIZE, width=CHAIN_SIZE, frames=CHAIN_FRAMES))
    try:
        again = run_chain(sim, CHAIN_SEED, 2).episodes[0]
    finally:
        sim.close()
    assert again.instruction == ep.instruction and np.array_equal(again.actions, ep.actions)
    assert again.metadata["instruction_schedule"] == ep.metadata["instruction_schedule"]
    assert np.array_equal(again.cameras["close"].rgb, ep.cameras["close"].rgb)
