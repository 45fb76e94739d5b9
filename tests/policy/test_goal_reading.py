"""Goal reading from an object layer, on synthetic tracks: a pushed, a pulled, a lifted, a placed and a
stacked object; and from the arm where the clip loses the object it moves (synthetic gripper tracks)."""

from __future__ import annotations

import numpy as np

from reconstruction.objects import STATES, ObjectLayer, ObjectTrack
from tesseract4d.policy.goal_reading import arm_goal, read_goal
from reconstruction.hand_track import GripperTrack

T = 16


def track(name: str, positions: np.ndarray) -> ObjectTrack:
    poses = np.repeat(np.eye(4)[None], T, 0)
    poses[:, :3, 3] = positions
    pts = np.random.default_rng(0).uniform(-0.02, 0.02, (50, 3)).astype(np.float32)
    return ObjectTrack(name=name, color=np.array([200, 30, 30], np.uint8), colour_name="red", points_object=pts,
                       colors=np.zeros((50, 3), np.uint8), normals_object=np.zeros((50, 3), np.float32),
                       T_world_object=poses, visibility=np.ones(T, np.float32), confidence=np.ones(T, np.float32),
                       state=np.zeros(T, np.int8))


def path(*waypoints) -> np.ndarray:
    """(T, 3) a piecewise-linear path through the waypoints, evenly over the clip."""
    w = np.asarray(waypoints, np.float64)
    s = np.linspace(0, len(w) - 1, T)
    i = np.minimum(s.astype(int), len(w) - 2)
    return w[i] + (s - i)[:, None] * (w[i + 1] - w[i])


def still(xyz) -> np.ndarray:
    return np.repeat(np.asarray(xyz, np.float64)[None], T, 0)


def test_a_pushed_object_gives_a_push_to_where_it_ends():
    layer = ObjectLayer([track("cube", path([0.0, 0.0, 0.02], [0.0, 0.0, 0.02], [0.0, 0.1, 0.02])),
                         track("other", still([0.1, -0.1, 0.02]))], source="test")
    goal = read_goal(layer)
    assert goal.skill == "push" and goal.target == "cube" and not goal.lifted and goal.on is None
    np.testing.assert_allclose(goal.displacement_m, [0.0, 0.1, 0.0], atol=1e-9)


def test_an_object_dragged_toward_the_robot_gives_a_pull():
    goal = read_goal(ObjectLayer([track("cube", path([0.05, 0.0, 0.02], [-0.05, 0.01, 0.02]))], source="test"))
    assert goal.skill == "pull" and goal.displacement_m[0] < -0.09


def test_a_lifted_object_held_up_at_the_end_gives_a_lift_to_its_height():
    goal = read_goal(ObjectLayer([track("cube", path([0.0, 0.0, 0.02], [0.0, 0.0, 0.02], [0.02, 0.0, 0.15]))],
                                 source="test"))
    assert goal.skill == "lift" and goal.lifted and goal.held_at_end
    np.testing.assert_allclose(goal.displacement_m, [0.02, 0.0, 0.13], atol=1e-9)


def test_a_carried_object_set_down_elsewhere_gives_a_pick_and_place():
    goal = read_goal(ObjectLayer([track("cube", path([0, 0, 0.02], [0, 0, 0.1], [0, -0.12, 0.1], [0, -0.12, 0.02]))],
                                 source="test"))
    assert goal.skill == "pick_place" and goal.lifted and not goal.held_at_end
    np.testing.assert_allclose(goal.displacement_m, [0.0, -0.12, 0.0], atol=1e-9)


def test_an_object_set_on_another_gives_a_stack_on_that_one():
    layer = ObjectLayer([track("green", still([0.1, 0.1, 0.02])),
                         track("red", path([0, 0, 0.02], [0, 0, 0.1], [0.1, 0.1, 0.1], [0.105, 0.098, 0.06]))],
                        source="test")
    goal = read_goal(layer)
    assert goal.skill == "stack" and goal.target == "red" and goal.on == "green" and goal.lifted


def test_a_future_where_nothing_moves_says_the_goal_is_reached():
    layer = ObjectLayer([track("cube", path([0, 0, 0.02], [0.005, 0.0, 0.02]))], source="test")
    assert read_goal(layer).skill == "none"
    assert read_goal(ObjectLayer([], source="test")).skill == "none"


def test_the_instructed_object_wins_when_it_moves_even_if_another_moves_more():
    layer = ObjectLayer([track("a", path([0, 0, 0.02], [0.2, 0, 0.02])), track("b", path([0, 0.1, 0.02], [0.05, 0.1, 0.02]))],
                        source="test", instructed="b")
    assert read_goal(layer).target == "b"
    layer.instructed = None
    assert read_goal(layer).target == "a"


def test_a_rise_in_one_frame_only_is_noise_not_a_lift():
    p = path([0, 0, 0.02], [0.1, 0, 0.02])
    p[8, 2] += 0.04
    goal = read_goal(ObjectLayer([track("cube", p)], source="test"))
    assert goal.skill == "push" and not goal.lifted


# ----------------------------------------------------------------- the arm, where the object is lost

LOST = STATES.index("lost")


def gripper(*waypoints) -> GripperTrack:
    """A gripper track through the waypoints (the hand's point, 6 cm above the TCP as the camera sees it)."""
    return GripperTrack(path(*waypoints), np.full(T, 500), np.array([0.0, 0.0, 1.0]))


def lost_after(tr: ObjectTrack, t: int) -> ObjectTrack:
    tr.state[t:] = LOST
    return tr


def test_a_pushed_object_lost_under_an_arm_that_carries_on_ends_where_the_arm_takes_it():
    # the arm comes down behind the cube, slides 12 cm to +y, and rises; the clip loses the cube on contact
    layer = ObjectLayer([lost_after(track("cube", still([0.0, 0.0, 0.02])), 6),
                         track("other", still([0.15, -0.1, 0.02]))], source="test", instructed="cube")
    arm = gripper([0.0, -0.05, 0.25], [0.0, -0.05, 0.07], [0.0, -0.05, 0.07], [0.0, 0.07, 0.07], [0.0, 0.07, 0.15])
    assert read_goal(layer).skill == "none"  # the layer alone: nothing moves
    goal = read_goal(layer, gripper=arm)
    assert goal.source == "arm" and goal.skill == "push" and goal.target == "cube" and not goal.lifted
    np.testing.assert_allclose(goal.displacement_m, [0.0, 0.12, 0.0], atol=0.01)


def test_an_arm_that_leaves_an_object_alone_does_not_move_it():
    # the arm comes down at the cube and slides away; the clip still sees the cube where it was
    layer = ObjectLayer([track("cube", still([0.0, 0.0, 0.02]))], source="test", instructed="cube")
    arm = gripper([0.0, -0.05, 0.25], [0.0, -0.05, 0.07], [0.0, 0.1, 0.07], [0.0, 0.1, 0.2])
    goal = read_goal(layer, gripper=arm)
    assert goal.skill == "none" and goal.source == "objects"


def test_an_arm_that_passes_far_from_the_object_reads_nothing():
    layer = ObjectLayer([lost_after(track("cube", still([0.0, 0.0, 0.02])), 4)], source="test", instructed="cube")
    arm = gripper([0.3, -0.2, 0.25], [0.3, -0.2, 0.07], [0.3, 0.0, 0.07])
    assert arm_goal(layer, arm) is None
    assert read_goal(layer, gripper=arm).skill == "none"


def test_an_object_that_lags_the_arm_follows_the_arm():
    # the clip sees the pushed cube move 3 cm while the arm slides 12: the smear, not the push
    layer = ObjectLayer([track("cube", path([0.0, 0.0, 0.02], [0.0, 0.0, 0.02], [0.03, 0.0, 0.02]))], source="test")
    arm = gripper([-0.05, 0.0, 0.25], [-0.05, 0.0, 0.07], [-0.05, 0.0, 0.07], [0.07, 0.0, 0.07])
    goal = read_goal(layer, gripper=arm)
    assert goal.source == "arm" and goal.skill == "push"
    np.testing.assert_allclose(goal.displacement_m, [0.12, 0.0, 0.0], atol=0.01)


def test_a_grasped_object_lost_in_the_hand_is_lifted_where_the_arm_holds_it():
    layer = ObjectLayer([lost_after(track("cube", still([0.0, 0.0, 0.02])), 5)], source="test", instructed="cube")
    arm = gripper([0.0, 0.0, 0.25], [0.0, 0.0, 0.08], [0.0, 0.0, 0.08], [0.05, 0.0, 0.23])
    goal = read_goal(layer, gripper=arm)
    assert goal.source == "arm" and goal.skill == "lift" and goal.held_at_end
    np.testing.assert_allclose(goal.displacement_m, [0.05, 0.0, 0.15], atol=0.01)


def test_a_carried_object_lost_in_the_hand_and_set_down_on_another_is_stacked_on_it():
    layer = ObjectLayer([lost_after(track("red", still([0.0, 0.0, 0.02])), 5), track("green", still([0.0, 0.15, 0.02]))],
                        source="test", instructed="red")
    arm = gripper([0.0, 0.0, 0.25], [0.0, 0.0, 0.08], [0.0, 0.0, 0.18], [0.0, 0.15, 0.18], [0.0, 0.15, 0.12],
                  [0.0, 0.15, 0.2])
    goal = read_goal(layer, gripper=arm)
    assert goal.source == "arm" and goal.skill == "stack" and goal.target == "red" and goal.on == "green"


def test_a_carried_object_set_down_on_the_table_is_a_pick_and_place():
    layer = ObjectLayer([lost_after(track("red", still([0.0, 0.0, 0.02])), 5), track("green", still([0.2, 0.2, 0.02]))],
                        source="test", instructed="red")
    arm = gripper([0.0, 0.0, 0.25], [0.0, 0.0, 0.08], [0.0, 0.0, 0.18], [0.0, -0.1, 0.18], [0.0, -0.1, 0.08],
                  [0.0, -0.1, 0.18])
    goal = read_goal(layer, gripper=arm)
    assert goal.source == "arm" and goal.skill == "pick_place" and goal.on is None
    np.testing.assert_allclose(goal.displacement_m, [0.0, -0.1, 0.0], atol=0.01)
