"""The synthetic RGB-D-N scene of the tests and benchmarks (no simulator needed).

* :func:`analytic_episode`: a checkered table and a sliding box, ray-cast exactly (RGB, metric
  depth, camera-frame normals, K, T_world_cam), in the dataset format;
* :func:`flickering_depth`: the same episode with depth corrupted the way a generated video's
  flickers (the stress input of the reconstruction tests and benchmark);
* :func:`look_at_pose`: a camera pose looking at a point;
* :func:`synthetic_episode` / :func:`write_synthetic_dataset`: a square sliding left or right in
  front of a tilted plane, with the instruction that says which way: the model tests' training data;
* :func:`group_episode`: episode k of a synthetic counterfactual group (two squares, one instruction each and
  "keep still") with known motion: the held-out believability tests' scene.

Benchmarks import it from the package too (``tesseract4d.testing.synthetic_scene``).
"""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import numpy as np

from tesseract4d import dataset_format as df
from tesseract4d.dataset_format import CameraFrames, Episode


def look_at_pose(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0])) -> np.ndarray:
    """Camera→world (4, 4), OpenCV axes (x right, y down, z forward), looking from eye at target."""
    forward = np.asarray(target, np.float64) - np.asarray(eye, np.float64)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, forward], axis=1)
    T[:3, 3] = eye
    return T


def analytic_episode(num_frames: int = 6, height: int = 96, width: int = 96, seed: int = 0,
                     instruction: str = "push the box to the right") -> Episode:
    """A ray-cast RGB-D-N episode: a checkered table plane z=0 and a 16 cm box sliding
    along the x = y diagonal (across the camera's view).

    The seed shifts the box's start, so different seeds give visibly different scenes.
    """
    fov = np.deg2rad(60.0)
    f = 0.5 * width / np.tan(fov / 2)
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], np.float64)
    T_world_cam = look_at_pose(np.array([0.7, -0.7, 0.6]), np.array([0.0, 0.0, 0.05]))
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays_cam = np.stack([(u - K[0, 2]) / f, (v - K[1, 2]) / f, np.ones_like(u)], -1)  # (H, W, 3), z = 1
    R, origin = T_world_cam[:3, :3], T_world_cam[:3, 3]
    rays = rays_cam @ R.T  # world directions scaled so that the camera z component is 1
    half = 0.08
    start = -0.25 + 0.1 * (seed % 5)
    rgb = np.zeros((num_frames, height, width, 3), np.uint8)
    depth = np.zeros((num_frames, height, width), np.float32)
    normal_cam = np.zeros((num_frames, height, width, 3), np.float32)
    for t in range(num_frames):
        s = start + 0.5 * t / max(num_frames - 1, 1)  # slides across the view, along x = y
        centre = np.array([s * np.sqrt(0.5), s * np.sqrt(0.5), half])
        # Plane z = 0: origin_z + s * ray_z = 0, s is the camera z-depth since ray_cam_z = 1.
        with np.errstate(divide="ignore", invalid="ignore"):
            s_plane = -origin[2] / rays[..., 2]
        hit_plane = np.isfinite(s_plane) & (s_plane > 0)
        p = origin + s_plane[..., None] * rays
        hit_plane &= (np.abs(p[..., 0]) < 1.0) & (np.abs(p[..., 1]) < 1.0)
        # Axis-aligned box by the slab method.
        lo, hi = centre - half, centre + half
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - origin) / rays, (hi - origin) / rays
        t_near = np.nanmax(np.minimum(t1, t2), axis=-1)
        t_far = np.nanmin(np.maximum(t1, t2), axis=-1)
        hit_box = (t_near <= t_far) & (t_near > 0)
        entry_axis = np.argmax(np.minimum(t1, t2), axis=-1)
        box_front = hit_box & (~hit_plane | (t_near < s_plane))
        d = np.where(box_front, t_near, np.where(hit_plane, s_plane, 0.0))
        depth[t] = d
        checker = ((np.floor(p[..., 0] / 0.1) + np.floor(p[..., 1] / 0.1)) % 2).astype(bool)
        plane_rgb = np.where(checker[..., None], [200, 200, 190], [110, 110, 100])
        rgb[t] = np.where(box_front[..., None], [220, 40, 40], np.where(hit_plane[..., None], plane_rgb, 0))
        n_world = np.zeros((height, width, 3))
        n_world[hit_plane] = [0.0, 0.0, 1.0]
        axis_n = np.eye(3)[entry_axis] * -np.sign(np.take_along_axis(rays, entry_axis[..., None], -1))
        n_world[box_front] = axis_n[box_front]
        normal_cam[t] = n_world @ R  # world -> camera: R^T n, row-vector form
    return Episode(
        env_id="Analytic-v0", seed=seed, instruction=instruction,
        cameras={"base_camera": CameraFrames(
            rgb=rgb, depth_m=depth, normal_cam=normal_cam,
            K=np.repeat(K[None], num_frames, 0), T_world_cam=np.repeat(T_world_cam[None], num_frames, 0),
        )},
        frame_steps=np.arange(num_frames, dtype=np.int32), fps=10.0, source="simulation",
    )


def flickering_depth(episode: Episode, noise_rel: float = 0.01, wobble_scale: float = 0.03,
                     wobble_shift_m: float = 0.02, seed: int = 0) -> Episode:
    """A copy of ``episode`` whose depth is corrupted the way a generated video's flickers:
    per-pixel noise (a fraction ``noise_rel`` of the depth) and a per-frame scale and shift
    wobble (sinusoids of amplitude ``wobble_scale`` and ``wobble_shift_m``, about zero-mean over
    a clip). The stress input of the reconstruction tests and benchmark."""
    rng = np.random.default_rng(seed)
    out = copy.deepcopy(episode)
    for cam in out.cameras.values():
        T = len(cam.depth_m)
        phase = rng.uniform(0, 2 * np.pi)
        scale = 1 + wobble_scale * np.sin(1.7 * np.arange(T) + phase)
        shift = wobble_shift_m * np.cos(2.3 * np.arange(T) + phase)
        valid = cam.depth_m > 0
        noisy = cam.depth_m * (1 + noise_rel * rng.standard_normal(cam.depth_m.shape))
        cam.depth_m = np.where(valid, noisy * scale[:, None, None] + shift[:, None, None], 0).astype(np.float32)
    return out


INSTRUCTIONS = {1: "push the square to the right", -1: "push the square to the left"}


def synthetic_episode(seed: int, frames: int = 8, size: int = 32, direction: int = 1) -> df.Episode:
    """A square moving sideways in front of a tilted plane: RGB, metric depth, normals, K."""
    rng = np.random.default_rng(seed)
    f = size * 1.0
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], np.float64)
    v, u = np.mgrid[0:size, 0:size]
    plane_depth = (0.9 + 0.3 * v / size).astype(np.float32)
    plane_normal = np.array([0.0, -0.3, -1.0], np.float32)
    plane_normal /= np.linalg.norm(plane_normal)
    colour = rng.integers(120, 256, 3)
    x0, y0 = int(rng.integers(4, size // 2)), int(rng.integers(6, size - 14))
    rgb = np.zeros((frames, size, size, 3), np.uint8)
    depth = np.zeros((frames, size, size), np.float32)
    normal = np.zeros((frames, size, size, 3), np.float32)
    for t in range(frames):
        rgb[t] = (40 + 100 * v[..., None] / size).astype(np.uint8)
        depth[t] = plane_depth
        normal[t] = plane_normal
        x = x0 + direction * t
        rgb[t, y0:y0 + 8, x:x + 8] = colour
        depth[t, y0:y0 + 8, x:x + 8] = 0.5
        normal[t, y0:y0 + 8, x:x + 8] = (0.0, 0.0, -1.0)
    cam = df.CameraFrames(rgb=rgb, depth_m=depth, normal_cam=normal, K=np.repeat(K[None], frames, 0),
                          T_world_cam=np.repeat(np.eye(4)[None], frames, 0))
    return df.Episode(env_id="Synthetic-v0", seed=seed, instruction=INSTRUCTIONS[direction], cameras={"close": cam},
                      frame_steps=np.arange(frames, dtype=np.int32), success=True)


def write_synthetic_dataset(root: Path, episodes: int = 4, frames: int = 8, size: int = 32, seed_start: int = 0) -> Path:
    df.init_dataset(root, df.DatasetInfo(height=size, width=size, cameras=["close"]))
    for seed in range(seed_start, seed_start + episodes):
        df.write_episode(root, synthetic_episode(seed, frames, size, direction=1 if seed % 2 == 0 else -1))
    return root


SEGMENTS = {0: "background", 17: "ground", 18: "cube"}


def _segment(ep: df.Episode) -> df.Episode:
    cam = ep.cameras["close"]
    cam.segmentation = np.where(np.isclose(cam.depth_m, 0.5), 18, 17).astype(np.int32)
    cam.seg_id_to_name = dict(SEGMENTS)
    return ep


def write_segmented_dataset(root: Path, episodes: int = 3, frames: int = 8, size: int = 32) -> Path:
    """The synthetic moving-square dataset with a segmentation: square = 'cube', plane = 'ground'."""
    df.init_dataset(root, df.DatasetInfo(height=size, width=size, cameras=["close"]))
    for seed in range(episodes):
        df.write_episode(root, _segment(synthetic_episode(seed, frames, size, direction=1 if seed % 2 == 0 else -1)))
    return root


def write_grouped_dataset(root: Path, scenes: int = 2, frames: int = 8, size: int = 32, singles: int = 0) -> Path:
    """Counterfactual groups of the segmented dataset: each scene (seed) twice, the square moving right
    (variant 0) and left (variant 1) from the same first frame, each with its own instruction; plus
    ``singles`` episodes outside any group (seeds after the scenes')."""
    df.init_dataset(root, df.DatasetInfo(height=size, width=size, cameras=["close"]))
    for seed in range(scenes):
        for k, direction in enumerate((1, -1)):
            df.write_episode(root, _segment(dataclasses.replace(synthetic_episode(seed, frames, size, direction),
                                                                variant=k)))
    for seed in range(scenes, scenes + singles):
        df.write_episode(root, _segment(synthetic_episode(seed, frames, size)))
    return root


# A counterfactual group: one scene, three instructions, known motion (held-out believability and the
# distillation's pair scoring).
GROUP_SIZE, GROUP_FRAMES, GROUP_F_PX = 32, 8, 32.0  # image size, frames, focal length (pixels); the scene lies at 1 m
GROUP_SEG = {0: "background", 3: "panda_hand", 5: "table-workspace", 6: "goal_region", 18: "red_cube", 19: "green_cube"}
GROUP_OBJECTS = {"red_cube": (18, (220, 30, 30), (6, 10)), "green_cube": (19, (30, 200, 30), (20, 22))}  # id, colour, (u0, v0)
# (instruction, skill, target, commanded displacement in world metres = camera metres here)
GROUP = (
    ("push the red cube to the right", "push", "red_cube", (0.5, 0.0, 0.0)),
    ("push the green cube up", "push", "green_cube", (0.0, -0.5, 0.0)),
    ("keep still", "keep_still", None, (0.0, 0.0, 0.0)),
)


def group_episode(k: int, seed: int = 100000, scale: int = 1) -> df.Episode:
    """Episode k of a synthetic group: two 8-px squares on a grey plane 1 m in front of the camera
    (T_world_cam = identity, so world metres map to f pixels); the instructed one moves
    ``commanded * f`` pixels over the clip, the other stays; a grey robot block stays too.
    ``scale``: the same scene seen by a camera of ``scale`` times the resolution (and focal length)."""
    instruction, skill, target, cmd = GROUP[k]
    K = np.array([[GROUP_F_PX, 0, GROUP_SIZE / 2], [0, GROUP_F_PX, GROUP_SIZE / 2], [0, 0, 1]])
    v, u = np.mgrid[0:GROUP_SIZE, 0:GROUP_SIZE]
    rgb = np.zeros((GROUP_FRAMES, GROUP_SIZE, GROUP_SIZE, 3), np.uint8)
    seg = np.zeros((GROUP_FRAMES, GROUP_SIZE, GROUP_SIZE), np.int32)
    poses = {name: np.zeros((GROUP_FRAMES, 7), np.float32) for name in GROUP_OBJECTS}
    for t in range(GROUP_FRAMES):
        rgb[t] = (60 + 60 * v[..., None] / GROUP_SIZE).astype(np.uint8)
        seg[t] = 5
        rgb[t, 26:, :6], seg[t, 26:, :6] = 90, 3  # a robot link: not a scene object
        for name, (oid, colour, (u0, v0)) in GROUP_OBJECTS.items():
            shift = np.asarray(cmd[:2]) * GROUP_F_PX * t / (GROUP_FRAMES - 1) if name == target else np.zeros(2)
            uu, vv = int(round(u0 + shift[0])), int(round(v0 + shift[1]))
            rgb[t, vv:vv + 8, uu:uu + 8], seg[t, vv:vv + 8, uu:uu + 8] = colour, oid
            poses[name][t] = [(uu + 3.5 - GROUP_SIZE / 2) / GROUP_F_PX, (vv + 3.5 - GROUP_SIZE / 2) / GROUP_F_PX, 1.0, 1, 0, 0, 0]
    up = lambda a: np.repeat(np.repeat(a, scale, axis=1), scale, axis=2)  # noqa: E731  (T, H, W, ...) -> (T, sH, sW, ...)
    K[:2] *= scale  # pixel centres at half-integers: no offset
    n = GROUP_SIZE * scale
    cam = df.CameraFrames(rgb=up(rgb), depth_m=np.ones((GROUP_FRAMES, n, n), np.float32),
                          normal_cam=np.broadcast_to(np.float32([0, 0, -1]), (GROUP_FRAMES, n, n, 3)).copy(),
                          K=np.repeat(K[None], GROUP_FRAMES, 0), T_world_cam=np.repeat(np.eye(4)[None], GROUP_FRAMES, 0),
                          segmentation=up(seg), seg_id_to_name=dict(GROUP_SEG))
    intent = {"skill": skill, "variant": skill if skill == "keep_still" else f"{skill}_{k}", "target": target,
              "other": None, "commanded_displacement_world_m": list(cmd), "gripper_goal_world_m": None}
    return df.Episode(env_id="Synthetic-v0", seed=seed, instruction=instruction, cameras={"close": cam},
                      frame_steps=np.arange(GROUP_FRAMES, dtype=np.int32), object_poses=poses, success=True,
                      variant=k, intent=intent)
