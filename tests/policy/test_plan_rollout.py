"""The predict-then-plan arms in the simulator: two episodes of each, through the rollout evaluation,
with every read of an object's simulator pose watched: the arms may not read one (only the simulator's
own step, which scores the task, and the evaluation's success check may)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

PLAN_MODULES = ("plan.py", "perception.py", "primitives.py", "goal_reading.py", "words.py")
SIMULATOR_FILES = ("mani_skill/envs/sapien_env.py", "datagen/simulate.py", "datagen/capture.py")


@pytest.mark.sim
@pytest.mark.slow
def test_plan_arms_run_without_reading_the_simulators_object_poses(tmp_path, monkeypatch):
    import mani_skill.envs  # noqa: F401  (makes the structs importable)
    from mani_skill.utils.structs.actor import Actor

    from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT
    from tesseract4d.policy.loop import LoopConfig
    from tesseract4d.policy.rollout_eval import RolloutConfig, run_rollouts

    reads = {"allowed": 0, "by_arm": []}
    pose = Actor.pose

    def watched(self):
        frames, f = [], sys._getframe(1)
        while f is not None:
            frames.append((f.f_code.co_filename, f.f_code.co_name))
            f = f.f_back
        in_arm = any(Path(path).name in PLAN_MODULES and "tesseract4d/policy" in path for path, _ in frames)
        # the simulator's own reads (reset, step: they score the task), the harness's renders, and the
        # evaluation's success check of a tabletop skill
        simulator = any(path.endswith(SIMULATOR_FILES) for path, _ in frames) or \
            any(fn == "done" and path.endswith("tabletop_tasks.py") for path, fn in frames)
        if in_arm and not simulator:
            reads["by_arm"].append([f"{Path(path).name}:{fn}" for path, fn in frames[:8]])
        else:
            reads["allowed"] += 1
        return pose.fget(self)

    monkeypatch.setattr(Actor, "pose", property(watched, pose.fset))
    out = tmp_path / "rollout"
    cfg = RolloutConfig(tasks=["PushCube-v1"], episodes=2, arms=["oracle_plan", "words_plan", "world_model_plan"],
                        checkpoint=str(SHIPPED_CHECKPOINT), out=str(out), videos=1, viewer_episodes=1,
                        loop=LoopConfig(resolution=None, max_steps=200, plan_replans=1))
    report = run_rollouts(cfg, progress=False)

    assert reads["by_arm"] == [], reads["by_arm"][:3]
    assert reads["allowed"] > 0  # the watch saw the simulator's own reads (it is in place)
    saved = json.loads((out / "report.json").read_text())
    assert saved["summary"] == json.loads(json.dumps(report["summary"]))
    for arm in ("oracle_plan", "words_plan", "world_model_plan"):
        cell = report["summary"]["per_task"]["PushCube-v1"][arm]
        assert cell["trials"] == 2 and 0 <= cell["wilson95"][0] <= cell["wilson95"][1] <= 1
        timing = report["timing_s"][arm]
        assert {"predict_s", "reconstruct_s", "plan_s", "cycle_s", "motion_planning_s", "simulate_s"} <= set(timing)
        rows = [r for r in report["episodes"] if r["arm"] == arm]
        assert len(rows) == 2 and all(r["plan"] and r["replans"] == 1 for r in rows)
        assert (out / "videos" / arm / "PushCube-v1" / "seed_100000.mp4").stat().st_size > 0
    assert report["timing_s"]["world_model_plan"]["predict_s"] > 0
    assert report["timing_s"]["oracle_plan"]["predict_s"] == 0 and report["timing_s"]["words_plan"]["reconstruct_s"] == 0
    # the oracle's goal is read from the true future: a push along +x, and the cube gets there
    oracle = [r for r in report["episodes"] if r["arm"] == "oracle_plan"]
    assert all(r["plan"][0]["skill"] == "push" and r["plan"][0]["reading"]["displacement_m"][0] > 0.05 for r in oracle)
    assert sum(r["success"] for r in oracle) >= 1
    assert (out / "viewer" / "world_model_plan" / "PushCube-v1" / "seed_100000" / "replan_00" / "predicted").is_dir()
    assert "Plan arms: seconds per replan" in (out / "report.md").read_text()
