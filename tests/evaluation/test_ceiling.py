"""The ceiling per situation (evaluation/ceiling.py) on a synthetic scene whose situations are known frame by
frame: a red cube on a table, covered in part by the arm, lifted in the gripper and carried, set down, and a
'decoded' clip that loses it in known frames."""

from __future__ import annotations

import numpy as np

from tesseract4d import dataset_format as df
from tesseract4d.evaluation.ceiling import SITUATIONS, episode_ceiling, object_situations, summarize

H = W = 48
TABLE, RED, GREY = (150, 110, 70), (220, 30, 30), (200, 200, 200)
SEG = {0: "background", 3: "panda_hand", 5: "table-workspace", 18: "cube_a", 19: "cube_b"}
# Per frame: cube_a's top-left pixel (u, v), its height above the table (m), the arm's rectangle (u0, v0, u1, v1) or None.
T = 10
CUBE = [(10, 20, 0.0), (10, 20, 0.0), (10, 20, 0.0), (10, 20, 0.0), (10, 18, 0.05), (14, 18, 0.05),
        (18, 18, 0.05), (22, 20, 0.0), (22, 20, 0.0), (22, 20, 0.0)]
ARM = [None, None, (7, 16, 13, 26), (7, 16, 13, 26), (10, 14, 16, 18), (14, 14, 20, 18), (18, 14, 24, 18),
       None, None, None]
SIZE = 6
KNOWN = {  # frames of cube_a in each situation (frame 0 included; scoring starts at 1)
    "occluded": [2, 3],  # the arm covers 18 of its 36 pixels
    "in_gripper": [4, 5, 6],  # lifted 5 cm with the hand just above it
    "moving": [4, 5, 6, 7],  # up, across, across, down
}


def scene() -> df.Episode:
    rgb = np.zeros((T, H, W, 3), np.uint8)
    rgb[:] = TABLE
    seg = np.full((T, H, W), 5, np.int32)
    poses = {"cube_a": np.zeros((T, 7), np.float32), "cube_b": np.zeros((T, 7), np.float32)}
    for t, (u, v, z) in enumerate(CUBE):
        rgb[t, v:v + SIZE, u:u + SIZE] = RED
        seg[t, v:v + SIZE, u:u + SIZE] = 18
        poses["cube_a"][t, :3] = (u * 0.01, v * 0.01, 0.02 + z)
        poses["cube_a"][t, 3] = 1.0
        rgb[t, 34:40, 34:40] = (30, 60, 220)  # cube_b stands still, never covered
        seg[t, 34:40, 34:40] = 19
        poses["cube_b"][t] = (0.34, 0.34, 0.02, 1, 0, 0, 0)
        if ARM[t] is not None:
            u0, v0, u1, v1 = ARM[t]
            rgb[t, v0:v1, u0:u1] = GREY
            seg[t, v0:v1, u0:u1] = 3
    K = np.tile(np.array([[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]]), (T, 1, 1))
    cam = df.CameraFrames(rgb=rgb, depth_m=np.ones((T, H, W), np.float32),
                          normal_cam=np.tile(np.array([0, 0, -1], np.float32), (T, H, W, 1)),
                          K=K, T_world_cam=np.tile(np.eye(4), (T, 1, 1)), segmentation=seg, seg_id_to_name=SEG)
    intent = {"skill": "pick_place", "variant": "place_right", "target": "cube_a",
              "commanded_displacement_world_m": [0.12, 0.0, 0.0]}
    return df.Episode(env_id="Synthetic-v1", seed=0, instruction="put the red cube to the right", cameras={"c": cam},
                      frame_steps=np.arange(T, dtype=np.int32), object_poses=poses, intent=intent)


def lose(gt: df.Episode, frames: list[int]) -> np.ndarray:
    """The ground truth's RGB with cube_a painted over by the table in ``frames``."""
    cam = gt.cameras["c"]
    rgb = cam.rgb.copy()
    for t in frames:
        rgb[t][cam.segmentation[t] == 18] = TABLE
    return rgb


def test_situations_are_found_in_the_frames_they_happen():
    sit = object_situations(scene(), "c")
    assert set(sit) == {18, 19}
    for s, frames in KNOWN.items():
        assert np.nonzero(sit[18][s])[0].tolist() == frames, s
        assert not sit[19][s].any(), s  # the still, uncovered cube is in no situation
    assert sit[18]["all"].all()


def test_the_truth_keeps_everything_and_is_found_whole():
    gt = scene()
    row = episode_ceiling(gt, "c", gt.cameras["c"].rgb)
    assert row["objects_present"] == 1.0 and row["whole_at_end"] is True
    for s in SITUATIONS:
        present, judged = row["permanence"][s]
        assert present == judged > 0, s
    # 9 scored frames x 2 objects
    assert row["permanence"]["all"] == [18, 18]


def test_a_cube_lost_in_the_gripper_is_counted_there_and_nowhere_else():
    gt = scene()
    row = episode_ceiling(gt, "c", lose(gt, [4, 5, 6]))
    assert row["permanence"]["in_gripper"] == [0, 3]
    assert row["permanence"]["moving"] == [1, 4]  # frame 7 (set down) kept
    assert row["permanence"]["occluded"] == [2, 2]
    assert row["permanence"]["all"] == [15, 18]
    assert row["objects_present"] == 6 / 9
    assert row["whole"]["in_gripper"] == [0, 3] and row["whole_at_end"] is True


def test_a_cube_lost_behind_the_arm_and_at_the_end():
    gt = scene()
    row = episode_ceiling(gt, "c", lose(gt, [2, 3, 9]))
    assert row["permanence"]["occluded"] == [0, 2]
    assert row["permanence"]["in_gripper"] == [3, 3]
    assert row["whole_at_end"] is False
    summary = summarize([row, episode_ceiling(gt, "c", gt.cameras["c"].rgb)])
    assert summary["all"]["permanence_occluded"] == [2, 4]
    assert summary["all"]["whole_at_end"] == [1, 2]
    assert summary["place_right"]["episodes"] == 2


def test_the_cached_finder_agrees_with_find_object():
    from tesseract4d.evaluation.ceiling import ObjectFinder
    from tesseract4d.evaluation.heldout_believability import find_object

    gt = scene()
    cam = gt.cameras["c"]
    finder = ObjectFinder(cam.rgb[0], cam.segmentation[0] == 18)
    for pred in (cam.rgb, lose(gt, [2, 3, 5, 9])):
        for t in range(T):
            found = find_object(cam.rgb[0], cam.segmentation[0] == 18, pred[t])
            assert finder.whole(pred[t]) == bool(found is not None and found.whole), t


def test_without_intent_the_moved_object_is_the_one_that_moves_farthest():
    import dataclasses

    from tesseract4d.evaluation.ceiling import moved_object

    gt = dataclasses.replace(scene(), intent=None)
    assert moved_object(gt, "c") == 18
    row = episode_ceiling(gt, "c", lose(gt, [9]))
    assert row["whole_at_end"] is False and row["skill"] == "Synthetic-v1"
