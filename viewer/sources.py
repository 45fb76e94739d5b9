"""What the viewer can open, turned into one in-memory type: :class:`Recon4D`.

* a reconstruction folder (``manifest.json`` + ``recon4d.npz``) is loaded as is;
* a dataset episode (a ``.h5`` file, ``DIR/ENV_ID/SEED``, or a dataset folder holding one
  episode, which is how predictions are written) is back-projected on the fly, frame by frame,
  without any refinement.

Also holds :func:`analytic_episode`, a small synthetic RGB-D-N episode (a checkered table and a
sliding box, ray-cast exactly) for tests, benchmarks and trying the viewer without data.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from reconstruction.recon4d import MANIFEST, Recon4D
from tesseract4d.dataset_format import CameraFrames, Episode
from tesseract4d.errors import UserError
from tesseract4d.motion import depth_tolerance_m
from tesseract4d.geometry import depth_to_world_points, rotate_vectors, unproject_depth, transform_points

# Two camera poses closer than this (metres / rotation-matrix entries) count as the same camera.
STATIC_CAMERA_TOL = 1e-4


def load_source(path: str | os.PathLike, camera: str | None = None) -> Recon4D:
    """Open PATH as a reconstruction folder or a dataset episode; raise UserError with the fix."""
    from tesseract4d.dataset_format import read_episode, resolve_episode

    p = Path(path)
    if p.is_dir() and (p / MANIFEST).is_file():
        return Recon4D.load(p)
    if not p.exists() and not (p.parent.parent / "episodes").is_dir():
        raise UserError(
            f"{p} does not exist. Pass a reconstruction folder (from `tesseract4d reconstruct`), an episode "
            ".h5 file, a dataset/prediction folder with one episode, or DIR/ENV_ID/SEED."
        )
    if p.is_file() and p.suffix != ".h5":
        raise UserError(
            f"{p} is not something the viewer opens: expected a reconstruction folder (with {MANIFEST}) or a "
            "dataset episode (.h5 file, dataset folder with one episode, or DIR/ENV_ID/SEED)."
        )
    if p.is_dir() and not (p / "episodes").is_dir():
        raise UserError(
            f"{p} is neither a reconstruction folder (no {MANIFEST}) nor a dataset folder (no episodes/); "
            "pass the folder written by `tesseract4d reconstruct`, `predict` or `datagen`."
        )
    episode_file = resolve_episode(p)
    episode = read_episode(episode_file)
    recon = recon_from_episode(episode, camera=camera)
    recon.metadata["episode_path"] = str(episode_file)
    return recon


def recon_from_episode(episode: Episode, camera: str | None = None) -> Recon4D:
    """Back-project every frame of one camera of an episode to world points (no refinement).

    Moving points and the fused static background come from the per-pixel farthest depth over
    time when the camera is static (moving things occlude the background; where something never
    moves away it counts as background). A moving camera gives no background and no moving points.
    """
    if camera is None:
        camera = next(iter(episode.cameras))
    if camera not in episode.cameras:
        raise UserError(f"episode {episode.episode_id} has no camera {camera!r}; it has {sorted(episode.cameras)}")
    cam = episode.cameras[camera]
    T = cam.num_frames
    depth = np.asarray(cam.depth_m, np.float32)  # (T, H, W)
    valid = np.isfinite(depth) & (depth > 0)
    static_camera = bool(
        np.all(np.abs(cam.T_world_cam - cam.T_world_cam[:1]) < STATIC_CAMERA_TOL)
        and np.all(np.abs(cam.K - cam.K[:1]) < STATIC_CAMERA_TOL)
    )
    dynamic_px = np.zeros_like(valid)
    background = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), np.zeros((0, 3), np.float32))
    if static_camera and T > 1:
        depth_valid = np.where(valid, depth, 0.0)
        farthest_t = np.argmax(depth_valid, axis=0)  # (H, W) the frame that sees the background
        farthest = np.take_along_axis(depth_valid, farthest_t[None], 0)[0]  # (H, W), 0 = never valid
        # A pixel is moving when it is nearer than the farthest surface seen there over time (for a
        # static camera, the background that moving things pass in front of) beyond the tolerance.
        dynamic_px = valid & (depth < farthest - depth_tolerance_m(farthest))
        rows, cols = np.nonzero(farthest > 0)
        pts_cam = unproject_depth(farthest, cam.K[0])[rows, cols]
        background = (
            transform_points(cam.T_world_cam[0], pts_cam).astype(np.float32),
            cam.rgb[farthest_t[rows, cols], rows, cols].astype(np.uint8),
            rotate_vectors(cam.T_world_cam[0], cam.normal_cam[farthest_t[rows, cols], rows, cols]).astype(np.float32),
        )
    points, colors, normals, dynamic = [], [], [], []
    for t in range(T):
        pts, ok = depth_to_world_points(depth[t], cam.K[t], cam.T_world_cam[t])
        points.append(pts.astype(np.float32))
        colors.append(cam.rgb[t][ok].astype(np.uint8))
        normals.append(rotate_vectors(cam.T_world_cam[t], cam.normal_cam[t][ok]).astype(np.float32))
        dynamic.append(dynamic_px[t][ok])
    return Recon4D(
        points_world=points, colors=colors, normals_world=normals, dynamic=dynamic,
        rgb=np.asarray(cam.rgb, np.uint8), depth_m=depth, normal_cam=np.asarray(cam.normal_cam, np.float32),
        K=np.asarray(cam.K, np.float64), T_world_cam=np.asarray(cam.T_world_cam, np.float64), fps=float(episode.fps),
        background_points=background[0], background_colors=background[1], background_normals=background[2],
        metadata={
            "source": f"episode ({episode.source}), back-projected without refinement",
            "env_id": episode.env_id, "seed": episode.seed, "instruction": episode.instruction, "camera": camera,
        },
    )


def first_frame_episode(recon: Recon4D) -> Episode:
    """The first frame of a source as a one-frame episode (the model's conditioning input).

    Uses the original episode file when the source was opened from one, so the simulator
    metadata travels along; otherwise rebuilds the frame from the reconstruction's images.
    """
    from tesseract4d.dataset_format import read_episode

    path = recon.metadata.get("episode_path")
    if path and Path(path).is_file():
        return read_episode(path, frames=slice(0, 1))
    meta = recon.metadata
    return Episode(
        env_id=str(meta.get("env_id", meta.get("task", "unknown"))),
        seed=int(meta.get("seed", 0)),
        instruction=str(meta.get("instruction", "")),
        cameras={str(meta.get("camera", "base_camera")): CameraFrames(
            rgb=recon.rgb[:1], depth_m=recon.depth_m[:1], normal_cam=recon.normal_cam[:1],
            K=recon.K[:1], T_world_cam=recon.T_world_cam[:1],
        )},
        frame_steps=np.zeros(1, np.int32),
        fps=recon.fps,
    )


# --------------------------------------------------------------------------- synthetic scene


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
