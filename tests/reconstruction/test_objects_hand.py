"""The object layer's hand steps (reconstruction/objects.py ``follow_hand``) on a ray-cast box scene whose
video loses the object the hand moves: the object follows the hand's track where the layer lost it, and an
object the hand never reaches keeps its pose although the video redraws it elsewhere."""

from __future__ import annotations

import numpy as np

from reconstruction.objects import TrackConfig, episode_objects
from tesseract4d.testing.synthetic_objects import Box, box_episode, moving, still

T = 12
HALF = 0.02
HAND_HALF = (0.02, 0.02, 0.025)
UP = np.array([0.0, 0.0, 1.0])


def arm(hand_centre: np.ndarray) -> list[Box]:
    """A grey hand box at ``hand_centre`` (T, 3) with its link above it: the moving grey arm."""
    return [Box("panda_hand", hand_centre, np.zeros(T), HAND_HALF, (200, 200, 205)),
            Box("panda_link7", hand_centre + [0.0, 0.0, 0.07], np.zeros(T), (0.012, 0.012, 0.045), (190, 190, 200))]


def waypoints(*points) -> np.ndarray:
    """(T, 3) positions through ``points`` given as (frame, (x, y, z)), held between them."""
    frames = [f for f, _ in points]
    xyz = np.array([p for _, p in points], np.float64)
    return np.stack([np.interp(np.arange(T), frames, xyz[:, i]) for i in range(3)], 1)


def final_error(track, pose: np.ndarray) -> float:
    """Distance at the last frame between where the track carries the recorded origin and the record."""
    c = np.linalg.inv(track.T_world_object[0]) @ np.r_[pose[0, :3], 1.0]
    return float(np.linalg.norm((track.T_world_object[-1] @ c)[:3] - pose[-1, :3]))


def test_an_object_lost_under_a_hand_that_slides_on_ends_where_the_hand_takes_it():
    # The hand comes down behind the red cube and pushes it 11 cm along +y; the video draws the cube only
    # until the hand arrives (frames 0-3): the layer loses it, the hand carries on.
    hand = waypoints((0, (0.0, -0.05, 0.15)), (3, (0.0, -0.045, 0.03)), (4, (0.0, -0.045, 0.03)), (10, (0.0, 0.065, 0.03)),
                     (11, (0.0, 0.065, 0.12)))
    cube = still((0.0, 0.0, HALF), T) + np.where(np.arange(T)[:, None] >= 4, hand - hand[4], 0.0) * [1, 1, 0]
    red = Box("cube_red", cube, np.zeros(T), (HALF, HALF, HALF), (220, 30, 30), np.arange(T) < 4)
    green = Box("cube_green", still((-0.14, 0.10, HALF), T), np.zeros(T), (HALF, HALF, HALF), (30, 200, 40))
    ep = box_episode([red, green, *arm(hand)], T, intent={"target": "cube_red"})
    before = episode_objects(ep, "close", config=TrackConfig(follow_hand=False, keep_unreached=False)).track("cube_red")
    assert final_error(before, ep.object_poses["cube_red"]) > 0.08  # the layer alone: it stayed (lost) where it was
    layer = episode_objects(ep, "close")
    track = layer.track("cube_red")
    assert final_error(track, ep.object_poses["cube_red"]) < 0.015
    assert track.states()[-1] == "inferred" and (track.confidence[track.state == track.state[-1]] <= 0.3).all()
    rise = (track.T_world_object[:, :3, 3] - track.T_world_object[0, :3, 3]) @ UP
    assert np.abs(rise).max() < 0.005  # slid along the table
    green_track = layer.track("cube_green")
    assert np.allclose(green_track.T_world_object, green_track.T_world_object[0]) and "inferred" not in green_track.states()


def test_an_object_carried_and_set_down_ends_on_the_table_where_the_hand_let_go():
    # The hand comes down onto the red cube, lifts it 9 cm, carries it 10 cm along +x, sets it down and
    # rises; the video loses the cube once the hand closes over it (frame 4 on).
    hand = waypoints((0, (0.0, 0.0, 0.16)), (3, (0.0, 0.0, 0.065)), (4, (0.0, 0.0, 0.065)), (6, (0.0, 0.0, 0.155)),
                     (8, (0.10, 0.0, 0.155)), (10, (0.10, 0.0, 0.065)), (11, (0.10, 0.0, 0.16)))
    cube = still((0.0, 0.0, HALF), T)
    cube[4:11] = hand[4:11] - [0.0, 0.0, 0.045]
    cube[11] = cube[10]
    red = Box("cube_red", cube, np.zeros(T), (HALF, HALF, HALF), (220, 30, 30), np.arange(T) < 4)
    green = Box("cube_green", still((-0.12, -0.10, HALF), T), np.zeros(T), (HALF, HALF, HALF), (30, 200, 40))
    ep = box_episode([red, green, *arm(hand)], T, intent={"target": "cube_red"})
    track = episode_objects(ep, "close").track("cube_red")
    assert final_error(track, ep.object_poses["cube_red"]) < 0.015
    p = track.positions_world()
    assert ((p[6:9] - p[0]) @ UP > 0.06).all()  # carried up on the way
    assert abs(float((p[-1] - p[0]) @ UP)) < 0.005  # set down on the table
    assert track.states()[-1] == "inferred"


def test_an_object_the_hand_never_reaches_stays_although_the_video_redraws_it_elsewhere():
    # The hand pushes the red cube; the video redraws the far blue cube 4 cm away from frame 6 on (it never
    # moved: nothing touched it). The tracker alone follows the redraw; the hand's reach says it stayed.
    hand = waypoints((0, (0.0, -0.05, 0.15)), (3, (0.0, -0.045, 0.03)), (10, (0.0, 0.045, 0.03)), (11, (0.0, 0.045, 0.12)))
    cube = still((0.0, 0.0, HALF), T) + np.where(np.arange(T)[:, None] >= 3, hand - hand[3], 0.0) * [1, 1, 0]
    red = Box("cube_red", cube, np.zeros(T), (HALF, HALF, HALF), (220, 30, 30))
    drawn = still((0.12, 0.12, HALF), T)
    drawn[6:] += [0.04, 0.0, 0.0]
    blue = Box("cube_blue", drawn, np.zeros(T), (HALF, HALF, HALF), (30, 60, 220))
    ep = box_episode([red, blue, *arm(hand)], T, intent={"target": "cube_red"})
    ep.object_poses["cube_blue"][:, :3] = drawn[0]  # the truth: it stayed
    redrawn = episode_objects(ep, "close", config=TrackConfig(keep_unreached=False)).track("cube_blue")
    assert final_error(redrawn, ep.object_poses["cube_blue"]) > 0.03
    layer = episode_objects(ep, "close")
    blue_track = layer.track("cube_blue")
    assert np.allclose(blue_track.T_world_object, blue_track.T_world_object[0], atol=1e-9)
    assert blue_track.states()[:6] == ["tracked"] * 6 and blue_track.states()[6:] == ["lost"] * (T - 6)
    assert final_error(layer.track("cube_red"), ep.object_poses["cube_red"]) < 0.01  # the pushed one still moves
