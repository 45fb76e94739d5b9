"""Back-projection of an episode's frames to coloured world points: the one place that turns
depth images into the per-frame point lists of a :class:`Recon4D`.

* :func:`frame_points` is the step shared by the refined reconstruction (``reconstruct.py``) and
  the plain one below;
* :func:`recon_from_episode` is the plain one: the input depth as is, no refinement, what the
  viewer shows for a dataset episode or a prediction, with its object layer (``objects.py``): the
  simulator's own object poses for a recorded episode that has them, else the tracked objects;
* :func:`select_camera`: which camera of an episode both reconstructions read.
"""

from __future__ import annotations

import numpy as np

from reconstruction.flow import camera_is_static
from reconstruction.objects import ObjectLayer, episode_objects
from reconstruction.recon4d import Recon4D
from tesseract4d.dataset_format import CameraFrames, Episode
from tesseract4d.errors import UserError
from tesseract4d.geometry import rotate_vectors, transform_points, unproject_depth
from tesseract4d.motion import depth_tolerance_m


def select_camera(episode: Episode, camera: str | None) -> tuple[str, CameraFrames]:
    """(name, frames) of the camera ``camera`` of the episode; None = its first camera."""
    if not episode.cameras:
        raise UserError(f"episode {episode.episode_id} has no cameras; nothing to reconstruct")
    name = next(iter(episode.cameras)) if camera is None else camera
    if name not in episode.cameras:
        raise UserError(f"episode {episode.episode_id} has no camera {name!r}; it has {sorted(episode.cameras)}")
    return name, episode.cameras[name]


def frame_points(rgb: np.ndarray, depth_m: np.ndarray, normal_cam: np.ndarray, valid: np.ndarray, K: np.ndarray,
                 T_world_cam: np.ndarray, dynamic: np.ndarray) -> tuple[list, list, list, list]:
    """Per frame, the valid pixels as world points (N_t, 3) float32, their colours (N_t, 3)
    uint8, world normals (N_t, 3) float32 and dynamic labels (N_t,) bool, in pixel order.

    rgb (T, H, W, 3), depth_m (T, H, W), normal_cam (T, H, W, 3), valid and dynamic (T, H, W),
    K (T, 3, 3), T_world_cam (T, 4, 4).
    """
    points, colors, normals, dyn = [], [], [], []
    for t in range(len(depth_m)):
        pts_cam = unproject_depth(np.where(valid[t], depth_m[t], 0.0), K[t])[valid[t]]
        points.append(transform_points(T_world_cam[t], pts_cam).astype(np.float32))
        colors.append(np.asarray(rgb[t], np.uint8)[valid[t]])
        normals.append(rotate_vectors(T_world_cam[t], normal_cam[t][valid[t]]).astype(np.float32))
        dyn.append(np.asarray(dynamic[t], bool)[valid[t]])
    return points, colors, normals, dyn


def recon_from_episode(episode: Episode, camera: str | None = None, objects: bool = True) -> Recon4D:
    """Back-project every frame of one camera of an episode to world points (no refinement).

    ``objects``: also make the object layer (:func:`episode_object_layer`). Moving points and the static background come from the per-pixel farthest depth over
    time when the camera is static (moving things occlude the background; where something never
    moves away it counts as background). A moving camera gives no background and no moving points.
    """
    camera, cam = select_camera(episode, camera)
    T = cam.num_frames
    depth = np.asarray(cam.depth_m, np.float32)  # (T, H, W)
    valid = np.isfinite(depth) & (depth > 0)
    dynamic_px = np.zeros_like(valid)
    background = (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), np.zeros((0, 3), np.float32))
    if T > 1 and camera_is_static(cam.K, cam.T_world_cam):
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
    points, colors, normals, dynamic = frame_points(cam.rgb, depth, cam.normal_cam, valid, cam.K, cam.T_world_cam, dynamic_px)
    return Recon4D(
        points_world=points, colors=colors, normals_world=normals, dynamic=dynamic,
        rgb=np.asarray(cam.rgb, np.uint8), depth_m=depth, normal_cam=np.asarray(cam.normal_cam, np.float32),
        K=np.asarray(cam.K, np.float64), T_world_cam=np.asarray(cam.T_world_cam, np.float64), fps=float(episode.fps),
        background_points=background[0], background_colors=background[1], background_normals=background[2],
        objects=episode_object_layer(episode, camera) if objects else None,
        metadata={
            "source": f"episode ({episode.source}), back-projected without refinement",
            "env_id": episode.env_id, "seed": episode.seed, "instruction": episode.instruction, "camera": camera,
        },
    )


def episode_object_layer(episode: Episode, camera: str) -> ObjectLayer:
    """The object layer of an episode as it is: the simulator's recorded object poses where a recorded
    episode has them and a segmentation that names its objects (the truth's own tracks), else the
    objects tracked through its frames (a prediction, a user's video)."""
    cam = episode.cameras[camera]
    truth = (episode.source != "prediction" and bool(episode.object_poses) and cam.segmentation is not None
             and bool(cam.seg_id_to_name))
    return episode_objects(episode, camera, truth=truth)
