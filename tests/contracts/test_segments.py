"""tesseract4d.segments: which named segments are scenery, the robot or the scene's objects."""

from __future__ import annotations

import numpy as np

from tesseract4d.segments import robot_object_mask, scene_object_ids, scene_object_mask

SEG = {0: "background", 3: "panda_hand", 5: "table-workspace", 6: "goal_region", 18: "red_cube", 19: "green_cube"}


def test_scene_objects_leave_out_robot_table_ground_and_goals():
    assert scene_object_ids(SEG) == [18, 19]
    pick = {0: "background", 16: "table-workspace", 17: "ground", 18: "cube", 19: "goal_site", 1: "panda_link0",
            14: "camera_link", 12: "panda_leftfinger"}
    assert scene_object_ids(pick) == [18]
    assert scene_object_ids({18: "cube", 19: "l_shape_tool", 20: "goal_marker", 21: "red_cylinder"}) == [18, 19, 21]


def test_scene_object_mask_is_the_objects_alone_and_the_robot_mask_holds_them_and_the_robot():
    seg = np.array([[[0, 3, 5], [6, 18, 19]], [[19, 19, 3], [0, 5, 18]]], dtype=np.int16)  # (T=2, H=2, W=3)
    objects = scene_object_mask(seg, SEG)
    assert objects.shape == seg.shape and objects.dtype == bool
    assert np.array_equal(objects, np.isin(seg, [18, 19]))
    robot_and_objects = robot_object_mask(seg, SEG)
    assert np.array_equal(robot_and_objects, np.isin(seg, [3, 6, 18, 19]))  # goal_region is not scenery there
    assert not (objects & ~robot_and_objects).any()  # the scene's objects are a part of it


def test_a_scene_without_objects_has_an_empty_mask():
    seg = np.zeros((1, 4, 4), dtype=np.int32)
    assert not scene_object_mask(seg, {0: "background", 1: "panda_link0"}).any()
