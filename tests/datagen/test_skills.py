"""Skill library and counterfactual groups: one initial state, futures decided by the instruction."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from datagen import skills as sk
from datagen.instructions import direction_words
from datagen.palette import COLORS
from datagen.skill_language import TEMPLATES, make_skill_instruction, skill_attributes
from datagen.tabletop import ENV_ID as TABLETOP
from tesseract4d.cli import main
from tesseract4d.dataset_format import (
    DatasetInfo, Episode, CameraFrames, init_dataset, list_episode_files, read_episode, read_episode_attrs, read_info,
    write_episode,
)

# One group shared by the simulator tests: seed 1 of the tabletop, one future per kind of motion.
GROUP_SEED = 1
GROUP_SKILLS = ["push_left", "pull_back", "place_right", "keep_still"]
DIRECTION_WORDS = ("forward", "back", "left", "right")


# --------------------------------------------------------------------------- pure


def test_directions_are_the_instruction_frame():
    words = {name: direction_words(np.asarray(v[:2]) * 0.1) for name, v in sk.DIRECTIONS.items()}
    assert words == {"forward": "forward", "back": "back", "left": "to the left", "right": "to the right"}


def test_at_least_eight_variants_and_paraphrase_sets():
    assert len(sk.VARIANTS) >= 8
    for v in sk.VARIANTS.values():
        t = TEMPLATES[v.skill]
        assert len(t["train"]) >= 3 and len(t["heldout"]) >= 2, v.skill
        assert not set(t["train"]) & set(t["heldout"]), v.skill


@pytest.mark.parametrize("name", ["push_left", "pull_back", "place_forward", "stack", "lift", "hover_above"])
def test_every_paraphrase_names_object_direction_and_distance(name):
    v = sk.VARIANTS[name]
    cmd = np.asarray(sk.DIRECTIONS.get(v.direction, (0, 0, 0))) * v.distance_m
    intent = {"skill": v.skill, "target": "cube_a", "other": "cube_b" if v.needs_other else None,
              "direction": v.direction, "distance_m": v.distance_m, "commanded_displacement_world_m": list(cmd)}
    attrs = skill_attributes(intent, {"cube_a": "green cube", "cube_b": "purple cube"})
    for split in ("train", "heldout"):
        for i in range(len(TEMPLATES[v.skill][split])):
            text = TEMPLATES[v.skill][split][i].format(**attrs)
            assert "green cube" in text, text
            if v.needs_other:
                assert "purple cube" in text, text
            if v.direction:
                assert direction_words(cmd[:2]) in text, text
            if v.skill in ("push", "pull", "pick_place", "lift"):
                assert f"{round(v.distance_m * 100)} cm" in text, text
    assert make_skill_instruction(v.skill, attrs, np.random.default_rng(0)) in [
        " ".join(t.format(**attrs).split()) for t in TEMPLATES[v.skill]["train"]]


def test_check_intent_from_object_positions():
    intent = {"skill": "push", "target": "a", "other": None, "commanded_displacement_world_m": [0.0, 0.1, 0.0]}
    start = {"a": np.zeros(3), "b": np.array([0.2, 0.0, 0.02])}
    good = sk.check_intent(intent, start, {"a": np.array([0.01, 0.09, 0.0]), "b": start["b"] + 0.001}, np.zeros(3), np.ones(3))
    assert good["success"] and good["direction_cos"] > 0.9
    sideways = sk.check_intent(intent, start, {"a": np.array([0.09, 0.01, 0.0]), "b": start["b"]}, np.zeros(3), np.ones(3))
    assert not sideways["success"]
    knocked = sk.check_intent(intent, start, {"a": np.array([0.0, 0.1, 0.0]), "b": start["b"] + 0.01}, np.zeros(3), np.ones(3))
    assert not knocked["success"] and knocked["others_max_displacement_m"] > sk.OTHERS_STILL_M
    still = {"skill": "keep_still", "target": None, "other": None, "commanded_displacement_world_m": [0, 0, 0]}
    assert sk.check_intent(still, start, start, np.zeros(3), np.array([0.005, 0, 0]))["success"]
    assert not sk.check_intent(still, start, start, np.zeros(3), np.array([0.02, 0, 0]))["success"]


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("args, words", [
    (["--skills", "juggle"], ["unknown skill 'juggle'", "push_left", "keep_still"]),
    (["--skills", "push_left@teapot"], ["object 'teapot' is not in", "cube_a", "cylinder"]),
    (["--tasks", "PushCube-v1", "--skills", "stack"], ["does not apply to PushCube-v1", "push_left"]),
    (["--skills", "push_left,keep_still", "--instructions-per-scene", "3"], ["needs 3 distinct skills", "push_left, keep_still"]),
    (["--tasks", "PlugCharger-v1", "--instructions-per-scene", "2"], ["skills do not run in PlugCharger-v1", TABLETOP]),
])
def test_bad_skill_input_is_one_line_with_the_choices(tmp_path, capsys, args, words):
    argv = ["datagen", "--tasks", TABLETOP, "--episodes", "1", "--out", str(tmp_path / "ds")]
    for i in range(0, len(args), 2):
        if args[i] in argv:
            argv[argv.index(args[i]) + 1] = args[i + 1]
        else:
            argv += args[i:i + 2]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    for w in words:
        assert w in err, err
    assert not (tmp_path / "ds").exists()


# --------------------------------------------------------------------------- format


def _tiny_episode(variant=None, intent=None) -> Episode:
    t, h, w = 2, 8, 8
    cam = CameraFrames(rgb=np.zeros((t, h, w, 3), np.uint8), depth_m=np.ones((t, h, w), np.float32),
                       normal_cam=np.zeros((t, h, w, 3), np.float32), K=np.repeat(np.eye(3)[None], t, 0),
                       T_world_cam=np.repeat(np.eye(4)[None], t, 0))
    return Episode(env_id=TABLETOP, seed=7, instruction="stay still", cameras={"close": cam},
                   frame_steps=np.arange(t, dtype=np.int32), variant=variant, intent=intent)


def test_group_fields_round_trip_and_version_1_is_still_read(tmp_path):
    intent = {"skill": "keep_still", "variant": "keep_still", "success": True}
    init_dataset(tmp_path / "v2", DatasetInfo(height=8, width=8, cameras=["close"]))
    path = write_episode(tmp_path / "v2", _tiny_episode(variant=3, intent=intent))
    assert path.name == "seed_000007_k3.h5" and list_episode_files(tmp_path / "v2") == [path]
    ep = read_episode(path)
    assert (ep.variant, ep.intent, ep.group_id) == (3, intent, f"{TABLETOP}/seed_000007")
    assert read_episode_attrs(path)["intent"] == intent

    # A version-1 dataset as the shipped model's training data was written: no group fields.
    v1 = tmp_path / "v1"
    v1.mkdir()
    (v1 / "info.json").write_text(json.dumps(dict(json.loads(DatasetInfo(height=8, width=8).to_json()), format_version=1)))
    p1 = write_episode(v1, _tiny_episode())
    with h5py.File(p1, "a") as f:
        f.attrs["format_version"] = 1
        for key in ("group_id", "variant", "intent"):
            del f.attrs[key]
    assert read_info(v1).format_version == 1
    old = read_episode(p1)
    assert old.variant is None and old.intent is None and old.episode_id == f"{TABLETOP}/seed_000007"
    with pytest.raises(Exception, match="does not mix them"):
        init_dataset(v1, DatasetInfo(height=8, width=8))


def test_heldout_selection_keeps_whole_groups(tmp_path):
    from tesseract4d.evaluation.heldout import select_episodes

    folder = tmp_path / "episodes" / TABLETOP
    folder.mkdir(parents=True)
    for seed in (100000, 100001):
        for k in range(3):
            (folder / f"seed_{seed:06d}_k{k}.h5").touch()
    kept = select_episodes(tmp_path, max_per_task=2)
    assert [p.name for p in kept] == ["seed_100000_k0.h5", "seed_100000_k1.h5", "seed_100000_k2.h5"]


# --------------------------------------------------------------------------- simulator


@pytest.fixture(scope="module")
def sim_and_group():
    """One counterfactual group of the tabletop at 64x64, 4 frames, and the simulator that made it."""
    from datagen.counterfactual import run_group
    from datagen.simulate import EpisodeSimulator, SimConfig

    sim = EpisodeSimulator(TABLETOP, SimConfig(height=64, width=64, frames=4))
    try:
        result = run_group(sim, GROUP_SEED, len(GROUP_SKILLS), GROUP_SKILLS)
        yield sim, result
    finally:
        sim.close()


@pytest.fixture(scope="module")
def group(sim_and_group):
    return sim_and_group[1]


@pytest.mark.sim
def test_a_group_does_not_depend_on_the_groups_simulated_before_it(sim_and_group):
    """Held-out seed 100004's first future, made by a fresh simulator and by one that has simulated
    another group first: the same actions and object trajectories (they diverged at the push's
    contact while the physics scene outlived env.reset)."""
    from datagen.counterfactual import run_group
    from datagen.simulate import EpisodeSimulator, SimConfig

    used, _ = sim_and_group  # has simulated GROUP_SEED's group
    fresh = EpisodeSimulator(TABLETOP, SimConfig(height=64, width=64, frames=4))
    try:
        a = run_group(fresh, 100004, 1).episodes[0]
    finally:
        fresh.close()
    run_group(used, 100003, 1)  # the scene simulated just before it when the held-out set is made
    b = run_group(used, 100004, 1).episodes[0]
    assert a.intent["variant"] == b.intent["variant"] and np.array_equal(a.actions, b.actions)
    assert all(np.array_equal(a.object_poses[n], b.object_poses[n]) for n in a.object_poses)
    assert np.array_equal(a.cameras["close"].rgb, b.cameras["close"].rgb)


def _by_skill(result) -> dict[str, Episode]:
    return {e.intent["variant"]: e for e in result.episodes}


@pytest.mark.sim
def test_group_first_frames_are_identical_and_futures_differ(group):
    assert group.success, group.tries
    eps = group.episodes
    assert sorted(e.intent["variant"] for e in eps) == sorted(GROUP_SKILLS)
    assert [e.variant for e in eps] == list(range(len(GROUP_SKILLS)))
    assert len({e.group_id for e in eps}) == 1
    ref = eps[0].cameras["close"]
    for e in eps[1:]:
        cam = e.cameras["close"]
        for key in ("rgb", "depth_m", "normal_cam", "segmentation"):
            assert np.array_equal(getattr(cam, key)[0], getattr(ref, key)[0]), key
        for name in e.object_poses:
            assert np.array_equal(e.object_poses[name][0], eps[0].object_poses[name][0])
    # the last frames differ: the futures are different
    finals = [np.concatenate([e.object_poses[n][-1, :3] for n in e.intent["objects_present"]]) for e in eps]
    for i in range(len(eps)):
        for j in range(i + 1, len(eps)):
            assert np.abs(finals[i] - finals[j]).max() > 0.02, (eps[i].intent["variant"], eps[j].intent["variant"])
            assert not np.array_equal(eps[i].cameras["close"].rgb[-1], eps[j].cameras["close"].rgb[-1])


@pytest.mark.sim
@pytest.mark.parametrize("name", ["push_left", "pull_back", "place_right"])
def test_target_moves_along_the_instruction_and_others_stay(group, name):
    ep = _by_skill(group)[name]
    intent = ep.intent
    present = intent["objects_present"]
    disp = {n: ep.object_poses[n][-1, :3].astype(np.float64) - ep.object_poses[n][0, :3] for n in present}
    cmd = np.asarray(intent["commanded_displacement_world_m"])
    d = disp[intent["target"]]
    cos = float(d[:2] @ cmd[:2] / (np.linalg.norm(d[:2]) * np.linalg.norm(cmd[:2])))
    assert cos > 0.9, (name, d)
    assert np.linalg.norm(d[:2]) > 0.5 * np.linalg.norm(cmd[:2])
    for n in present:
        if n != intent["target"]:
            assert np.linalg.norm(disp[n]) < 0.005, (name, n, disp[n])
    assert intent["success"] and len(present) >= 2


@pytest.mark.sim
def test_keep_still_moves_nothing(group):
    ep = _by_skill(group)["keep_still"]
    for n in ep.intent["objects_present"]:
        assert np.linalg.norm(ep.object_poses[n][-1, :3] - ep.object_poses[n][0, :3]) < 0.001, n
    assert ep.intent["gripper_displacement_m"] < 0.01
    assert np.abs(ep.qpos[-1] - ep.qpos[0]).max() < 0.01  # the arm's joints hold too


@pytest.mark.sim
def test_instructions_name_colour_and_direction(group):
    for e in group.episodes:
        intent, text = e.intent, e.instruction
        if intent["target"]:
            color = e.metadata["instruction_attributes"]["object_colors"][intent["target"]]
            assert color in COLORS and f"{color} " in text, text
        if intent["skill"] in ("push", "pull", "pick_place"):
            assert any(w in text for w in DIRECTION_WORDS), text
    texts = [e.instruction for e in group.episodes]
    assert len(set(texts)) == len(texts)


@pytest.mark.sim
def test_commanded_future_gives_the_words_of_the_group(sim_and_group):
    # What the demo asks for without running a skill is what a group writes for that future.
    from datagen.counterfactual import commanded_future

    sim, group = sim_and_group
    for e in group.episodes:
        spec = e.intent["variant"] + (f"@{e.intent['target']}" if e.intent["target"] else "")
        text, intent = commanded_future(sim, GROUP_SEED, spec)
        assert text == e.instruction and intent["target"] == e.intent["target"], spec
        assert intent["commanded_displacement_world_m"] == e.intent["commanded_displacement_world_m"]


@pytest.mark.sim
def test_recorded_actions_re_simulate_every_future(sim_and_group):
    sim, group = sim_and_group
    env = sim.env
    for ep in group.episodes:
        env.reset(seed=ep.seed)
        for action in ep.actions:
            env.step(action)
        base = env.unwrapped
        for name in ep.intent["objects_present"]:
            now = getattr(base, name).pose.raw_pose[0].cpu().numpy()
            assert np.allclose(now[:3], ep.object_poses[name][-1, :3], atol=1e-4), (ep.episode_id, name)


@pytest.mark.sim
def test_datagen_cli_renders_a_group(tmp_path, capsys):
    out = tmp_path / "ds"
    argv = ["datagen", "--tasks", TABLETOP, "--instructions-per-scene", "2", "--skills", "push_right,keep_still",
            "--episodes", "1", "--resolution", "32", "--frames", "3", "--goal-marker", "--out", str(out), "--quiet"]
    assert main(argv) == 0
    files = list_episode_files(out)
    assert [p.name for p in files] == ["seed_000000_k0.h5", "seed_000000_k1.h5"]
    eps = [read_episode(p) for p in files]
    assert np.array_equal(eps[0].cameras["close"].rgb[0], eps[1].cameras["close"].rgb[0])
    assert {e.intent["variant"] for e in eps} == {"push_right", "keep_still"}
    assert all(e.env_kwargs["goal_marker"] for e in eps)
    marker = eps[0].object_poses["goal"][0, :3]
    assert abs(marker[2]) < 0.01 and np.abs(marker[:2]).max() < 0.2  # lying on the table, among the objects
    assert all((out / "previews" / TABLETOP / f"{p.stem}.mp4").is_file() for p in files)
    report = json.loads((out / "datagen_report.json").read_text())
    assert report["tasks"][TABLETOP]["successes"] == 1 and set(report["skills"]) >= {"push_right", "keep_still"}
    capsys.readouterr()
    assert main(["dataset", "info", str(out)]) == 0
    info = capsys.readouterr().out
    assert "counterfactual groups 1" in info and "push_right" in info
    assert main(["dataset", "check", str(out)]) == 0
    # resume: the same command finds the group complete and simulates nothing
    assert main(argv) == 0
    assert json.loads((out / "datagen_report.json").read_text())["this_run"]["attempts"] == 0
