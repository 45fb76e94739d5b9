"""Camera presets: where datagen's cameras stand and look.

- ``base_camera``: the task's own default camera (ManiSkill's ``_default_sensor_configs``).
  At 64x64 its arm is small and a cube is about 3 pixels wide.
- ``close``: frames the table area around the objects and the gripper's path tightly (per-task
  eye/target in tasks.py), so motion is visible at 64x64. The default for training data.
- ``side``: the ``close`` view mirrored to the robot's other side (y -> -y), a second viewpoint.

A view is an eye point, a look-at target and an up vector in world metres plus a vertical field
of view. Pose jitter (``datagen --set camera_jitter_m=M``) moves eye and target by independent uniform offsets
in [-M, M] metres per axis, drawn from the episode's seed, so every episode sees the scene from
a slightly different pose and the same seed always gives the same pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tesseract4d.errors import UserError
from datagen.tasks import get_task

PRESETS = ("base_camera", "close", "side")
DEFAULT_NEAR_M = 0.01
DEFAULT_FAR_M = 10.0


@dataclass(frozen=True)
class CameraView:
    """A camera placement: eye/target/up (3,) in world metres, vertical fov in degrees."""

    name: str
    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    fov_deg: float
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    near: float = DEFAULT_NEAR_M
    far: float = DEFAULT_FAR_M

    def jittered(self, rng: np.random.Generator, magnitude_m: float) -> "CameraView":
        """This view with eye and target each moved by U(-m, m) metres per axis."""
        if magnitude_m <= 0:
            return self
        d_eye = rng.uniform(-magnitude_m, magnitude_m, 3)
        d_target = rng.uniform(-magnitude_m, magnitude_m, 3)
        return CameraView(
            self.name, tuple(float(v) for v in np.add(self.eye, d_eye)),
            tuple(float(v) for v in np.add(self.target, d_target)), self.fov_deg, self.up, self.near, self.far,
        )


def parse_camera_list(text: str) -> list[str]:
    names = [c.strip() for c in text.split(",") if c.strip()]
    if not names:
        raise UserError(f"--cameras is empty; choose from {', '.join(PRESETS)}")
    for n in names:
        if n not in PRESETS:
            raise UserError(f"unknown camera preset {n!r}; choose from {', '.join(PRESETS)}")
    return list(dict.fromkeys(names))


def _view_from_sapien_pose(name: str, raw_pose: np.ndarray, fov_rad: float, near: float, far: float) -> CameraView:
    """A SAPIEN camera pose (p xyz, q wxyz; camera looks along its +x, up is its +z) as a view."""
    from scipy.spatial.transform import Rotation

    p = np.asarray(raw_pose[:3], dtype=np.float64)
    w, x, y, z = (float(v) for v in raw_pose[3:7])
    R = Rotation.from_quat([x, y, z, w]).as_matrix()
    forward, up = R[:, 0], R[:, 2]
    # Aim at where the optical axis meets the table (z = 0); a camera that looks up keeps 0.5 m.
    dist = float(np.clip(-p[2] / forward[2], 0.1, 2.0)) if forward[2] < -1e-3 else 0.5
    target = p + dist * forward
    return CameraView(name, tuple(p), tuple(target), float(np.degrees(fov_rad)), tuple(up), near, far)


def preset_view(name: str, env_id: str, base_env=None) -> CameraView:
    """The un-jittered view of preset ``name`` for task ``env_id``.

    ``base_camera`` reads the task's default sensor config, so it needs the (unwrapped) env.
    """
    spec = get_task(env_id)
    if name == "close":
        return CameraView("close", spec.close_eye, spec.close_target, spec.close_fov_deg)
    if name == "side":
        ex, ey, ez = spec.close_eye
        tx, ty, tz = spec.close_target
        return CameraView("side", (ex, -ey, ez), (tx, -ty, tz), spec.close_fov_deg)
    if name == "base_camera":
        if base_env is None:
            raise ValueError("the base_camera preset needs the env to read its default sensor config")
        configs = base_env._default_sensor_configs
        configs = configs if isinstance(configs, (list, tuple)) else [configs]
        for cfg in configs:
            if cfg.uid == "base_camera":
                raw = cfg.pose.raw_pose.reshape(-1, 7)[0].cpu().numpy()
                return _view_from_sapien_pose("base_camera", raw, float(cfg.fov), cfg.near, cfg.far)
        raise UserError(f"{env_id} has no base_camera; use --cameras close")
    raise UserError(f"unknown camera preset {name!r}; choose from {', '.join(PRESETS)}")


def episode_views(names: list[str], env_id: str, seed: int, jitter_m: float, base_env=None) -> list[CameraView]:
    """The views of one episode: presets, jittered with a generator seeded by (seed, camera index)."""
    views = []
    for i, name in enumerate(names):
        view = preset_view(name, env_id, base_env)
        rng = np.random.default_rng([int(seed), 7919, i])
        views.append(view.jittered(rng, jitter_m))
    return views
