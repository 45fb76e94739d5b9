"""Where a clip's arm goes (tesseract4d/evaluation/arm_target.py), on a ray-cast table scene: a camera
looking down at a table, two objects on it, and an "arm" drawn as a patch of world points at a chosen
height over a chosen place."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from tesseract4d import dataset_format as df
from tesseract4d.evaluation.arm_target import ARM_BAND_M, arm_points_near, arm_visit, table_height_m
from tesseract4d.evaluation.heldout_believability import contrast_by_group, contrast_entry
from tesseract4d.geometry import invert_pose, project_points, transform_points, unproject_depth
from tesseract4d.testing.synthetic_scene import look_at_pose

SIZE, FRAMES = 96, 6
K = np.array([[90.0, 0, SIZE / 2], [0, 90.0, SIZE / 2], [0, 0, 1]])
OBJECTS = {"cube_a": (0.05, -0.10), "cube_b": (-0.05, 0.10)}
SEG = {0: "background", 1: "table-workspace", 2: "cube_a", 3: "cube_b", 4: "panda_hand"}


def table_scene(table_z: float = 0.0, dx: float = 0.0):
    """(rgb, depth_m, segmentation, T_world_cam) of FRAMES identical frames: a table at height table_z
    seen from above at an angle, the two objects as 2 cm squares of their own colours on it."""
    T = look_at_pose(np.array([0.45 + dx, 0.0, 0.55 + table_z]), np.array([dx, 0.0, table_z]))
    rays = unproject_depth(np.ones((SIZE, SIZE)), K).reshape(-1, 3) @ T[:3, :3].T  # world ray directions
    depth = ((table_z - T[2, 3]) / rays[:, 2]).reshape(SIZE, SIZE)  # ray length along camera z = depth
    world = transform_points(T, unproject_depth(depth, K).reshape(-1, 3)).reshape(SIZE, SIZE, 3)
    rgb = np.full((SIZE, SIZE, 3), 150, np.uint8)
    seg = np.ones((SIZE, SIZE), np.int32)
    for i, (name, (x, y)) in enumerate(OBJECTS.items()):
        m = (np.abs(world[..., 0] - x - dx) < 0.012) & (np.abs(world[..., 1] - y) < 0.012)
        rgb[m], seg[m] = (220, 40 + 150 * i, 40), 2 + i
    return (np.repeat(rgb[None], FRAMES, 0), np.repeat(depth[None].astype(np.float32), FRAMES, 0),
            np.repeat(seg[None], FRAMES, 0), T)


def draw_arm(rgb, depth, T, x, y, height, frames=range(2, FRAMES)):
    """Splat a 3 × 3 cm patch of white world points at (x, y, height) into ``frames`` where it is nearer."""
    rgb, depth = rgb.copy(), depth.copy()
    g = np.linspace(-0.015, 0.015, 25)
    pts = np.stack(np.meshgrid(g + x, g + y), -1).reshape(-1, 2)
    pts = np.concatenate([pts, np.full((len(pts), 1), height)], 1)
    uv, z = project_points(transform_points(invert_pose(T), pts), K)
    u, v = np.round(uv[:, 0] - 0.5).astype(int), np.round(uv[:, 1] - 0.5).astype(int)
    ok = (u >= 0) & (u < SIZE) & (v >= 0) & (v < SIZE)
    for t in frames:
        for uu, vv, zz in zip(u[ok], v[ok], z[ok]):
            if zz < depth[t, vv, uu]:
                depth[t, vv, uu], rgb[t, vv, uu] = zz, 250
    return rgb, depth


def episode(rgb, depth, seg, T, table_z=0.0, dx=0.0, target="cube_a"):
    poses = {n: np.tile(np.float32([x + dx, y, table_z + 0.01, 1, 0, 0, 0]), (FRAMES, 1)) for n, (x, y) in OBJECTS.items()}
    cam = df.CameraFrames(rgb=rgb, depth_m=depth, normal_cam=np.zeros((FRAMES, SIZE, SIZE, 3), np.float32),
                          K=np.repeat(K[None], FRAMES, 0), T_world_cam=np.repeat(T[None], FRAMES, 0),
                          segmentation=seg, seg_id_to_name=dict(SEG))
    intent = {"skill": "push", "variant": "push_left", "target": target, "other": None,
              "commanded_displacement_world_m": [0.0, 0.1, 0.0], "gripper_goal_world_m": None}
    return df.Episode(env_id="Synthetic-v0", seed=100000, instruction=f"push the {target} left", cameras={"close": cam},
                      frame_steps=np.arange(FRAMES, dtype=np.int32), object_poses=poses, success=True, variant=0,
                      intent=intent)


def test_table_height_is_read_from_the_table_pixels():
    for z in (0.0, 0.7):
        rgb, depth, seg, T = table_scene(z)
        assert abs(table_height_m(depth[0], seg[0], SEG, K, T) - z) < 1e-4


@settings(max_examples=12, deadline=None)
@given(which=st.sampled_from(sorted(OBJECTS)), table_z=st.sampled_from([0.0, 0.75]), dx=st.floats(-0.05, 0.05),
       height=st.floats(ARM_BAND_M[0] + 0.01, ARM_BAND_M[1] - 0.01))
def test_an_arm_just_above_an_object_goes_to_that_object_wherever_the_table_is(which, table_z, dx, height):
    rgb, depth, seg, T = table_scene(table_z, dx)
    x, y = OBJECTS[which]
    rgb, depth = draw_arm(rgb, depth, T, x + dx + 0.005, y, table_z + height)
    ep = episode(rgb, depth, seg, T, table_z, dx)
    visit = arm_visit(ep, "close", rgb, depth)
    assert visit.judged and visit.object == which
    assert all(n == which or c == 0 for n, c in visit.points.items())


def test_a_moved_object_and_an_arm_high_over_the_scene_are_not_where_the_arm_goes():
    rgb, depth, seg, T = table_scene()
    x, y = OBJECTS["cube_b"]
    low_rgb, low_depth = draw_arm(rgb, depth, T, x + 0.02, y, 0.02)  # an object's top moved beside it
    high_rgb, high_depth = draw_arm(rgb, depth, T, x, y, 0.30)  # the arm travelling high
    ep = episode(rgb, depth, seg, T)
    for r, d in ((rgb, depth), (low_rgb, low_depth), (high_rgb, high_depth)):
        visit = arm_visit(ep, "close", r, d)
        assert visit.judged and visit.object is None and sum(visit.points.values()) == 0


def test_per_frame_and_single_cameras_count_the_same_points():
    rgb, depth, seg, T = table_scene()
    rgb, depth = draw_arm(rgb, depth, T, *OBJECTS["cube_a"], 0.08)
    objects = {n: np.asarray(p) for n, p in OBJECTS.items()}
    single = arm_points_near(rgb, depth, K, T, objects, 0.0)
    per_frame = arm_points_near(rgb, depth, np.repeat(K[None], FRAMES, 0), np.repeat(T[None], FRAMES, 0), objects, 0.0)
    assert single == per_frame and single["cube_a"] > 0 and single["cube_b"] == 0


def test_a_scene_without_a_table_is_not_judged():
    rgb, depth, seg, T = table_scene()
    ep = episode(rgb, depth, np.where(seg == 1, 0, seg), T)
    assert not arm_visit(ep, "close", rgb, depth).judged


def test_the_contrast_counts_the_arm_at_the_instructed_object_where_the_truths_arm_is_found_there():
    """Truth: the arm over cube_a, the instructed object. A prediction whose arm goes to cube_b is a
    wrong choice of object; an instruction whose truth's arm is not found is not judged."""
    rgb, depth, seg, T = table_scene()
    truth_rgb, truth_depth = draw_arm(rgb, depth, T, *OBJECTS["cube_a"], 0.08)
    wrong_rgb, wrong_depth = draw_arm(rgb, depth, T, *OBJECTS["cube_b"], 0.08)
    good = episode(truth_rgb, truth_depth, seg, T, target="cube_a")
    unfound = episode(rgb, depth, seg, T, target="cube_b")  # its truth's arm goes nowhere
    entries = [("g", contrast_entry(good, "close", truth_rgb, truth_depth)),
               ("g", contrast_entry(good, "close", wrong_rgb, wrong_depth)),
               ("h", contrast_entry(unfound, "close", wrong_rgb, wrong_depth))]
    assert [e["arm_object"] for _, e in entries] == ["cube_a", "cube_b", "cube_b"]
    summary = contrast_by_group(entries)
    assert (summary["arm_measured"], summary["arm_judged"], summary["arm_instructed"]) == (3, 2, 1)
    # The contrast judges both of group g wrong (neither moves cube_a): the truth-like arm is a lost contact.
    assert (summary["arm_judged_wrong"], summary["arm_instructed_wrong"]) == (2, 1)
    assert "arm_object" not in contrast_entry(good, "close", truth_rgb)  # no depth given: not measured
