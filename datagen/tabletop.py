"""A multi-object tabletop scene for skill datagen, registered as ``Tesseract4dTabletop-v1``.

The scene is ManiSkill's table scene (``TableSceneBuilder``, Panda at x = -0.615 facing +x)
with a fixed pool of primitive objects (``OBJECTS``: three 4 cm cubes and an upright cylinder).
Each reset, seeded by the episode seed:

- 2 to 4 objects of the pool are placed on the table at random, non-overlapping positions
  (at least ``MIN_SPACING_M`` apart, centres within ``REGION_XY``) with random yaw; the rest
  are parked out of view under the floor far from the table;
- every object present gets a distinct named colour from ``datagen.palette.COLORS``
  (render-only, so physics and recorded actions do not depend on it), so instructions can say
  "the green cylinder";
- with ``goal_marker=True`` a red and white target lies flat at a free spot of the table; by
  default there is none, so nothing in the picture says what should happen: the text decides.

``env.present`` lists the pool names on the table, ``env.object_colors`` their colour names and
``env.object_shapes`` their shape words. Units: metres.
"""

from __future__ import annotations

import numpy as np

from datagen.palette import COLORS

ENV_ID = "Tesseract4dTabletop-v1"

# Pool: recorded name -> (shape word, half height in metres). Colours are chosen per episode.
OBJECTS: dict[str, tuple[str, float]] = {
    "cube_a": ("cube", 0.02),
    "cube_b": ("cube", 0.02),
    "cube_c": ("cube", 0.02),
    "cylinder": ("cylinder", 0.025),
}
CUBE_HALF_M = 0.02
CYLINDER_RADIUS_M = 0.02
MIN_OBJECTS, MAX_OBJECTS = 2, 4
REGION_XY = ((-0.1, 0.1), (-0.15, 0.15))  # (x range, y range) of object centres
MIN_SPACING_M = 0.09
# Colours drawn per episode (names of datagen.palette.COLORS): only ones that stay easy to
# tell apart at 64-128 pixels (orange next to yellow or red is not).
PALETTE = ("red", "green", "blue", "yellow", "purple", "cyan")
_PARK_Z = -5.0  # unused pool objects wait here, far below the floor and out of every camera

_registered = False


def register() -> str:
    """Register the env with ManiSkill (idempotent) and return its id."""
    global _registered
    if _registered:
        return ENV_ID
    import sapien
    import torch
    from mani_skill.envs.sapien_env import BaseEnv
    from mani_skill.sensors.camera import CameraConfig
    from mani_skill.utils import sapien_utils
    from mani_skill.utils.building import actors
    from mani_skill.utils.registration import REGISTERED_ENVS, register_env
    from mani_skill.utils.scene_builder.table import TableSceneBuilder
    from mani_skill.utils.structs.pose import Pose


    if ENV_ID in REGISTERED_ENVS:
        _registered = True
        return ENV_ID

    @register_env(ENV_ID, max_episode_steps=400)
    class Tesseract4dTabletopEnv(BaseEnv):
        """Table, Panda and 2-4 coloured primitives; see the module docstring."""

        SUPPORTED_ROBOTS = ["panda"]

        def __init__(self, *args, robot_uids="panda", robot_init_qpos_noise=0.02, goal_marker=False, **kwargs):
            self.robot_init_qpos_noise = robot_init_qpos_noise
            self.goal_marker = bool(goal_marker)
            self.present: list[str] = []
            self.object_colors: dict[str, str] = {}
            self.object_shapes = {name: shape for name, (shape, _) in OBJECTS.items()}
            self.object_half_heights = {name: h for name, (_, h) in OBJECTS.items()}
            super().__init__(*args, robot_uids=robot_uids, **kwargs)

        @property
        def _default_sensor_configs(self):
            pose = sapien_utils.look_at(eye=[0.3, 0, 0.6], target=[-0.1, 0, 0.1])
            return [CameraConfig("base_camera", pose, 128, 128, np.pi / 2, 0.01, 100)]

        @property
        def _default_human_render_camera_configs(self):
            pose = sapien_utils.look_at([0.6, 0.7, 0.6], [0.0, 0.0, 0.35])
            return CameraConfig("render_camera", pose, 512, 512, 1, 0.01, 100)

        def _load_agent(self, options: dict):
            super()._load_agent(options, sapien.Pose(p=[-0.615, 0, 0]))

        def _load_scene(self, options: dict):
            self.table_scene = TableSceneBuilder(env=self, robot_init_qpos_noise=self.robot_init_qpos_noise)
            self.table_scene.build()
            self.objects = {}
            for i, (name, (shape, half_h)) in enumerate(OBJECTS.items()):
                park = sapien.Pose(p=[10.0 + i, 0, _PARK_Z])
                if shape == "cube":
                    self.objects[name] = actors.build_cube(self.scene, half_size=CUBE_HALF_M, color=[1, 1, 1, 1],
                                                           name=name, initial_pose=park)
                else:  # ManiSkill's cylinder lies along x; the initial pose stands it up
                    self.objects[name] = actors.build_cylinder(self.scene, radius=CYLINDER_RADIUS_M, half_length=half_h,
                                                               color=[1, 1, 1, 1], name=name, initial_pose=park)
                setattr(self, name, self.objects[name])  # recorded like every task's actors: env.<name>
            self.goal_site = actors.build_red_white_target(
                self.scene, radius=0.05, thickness=1e-5, name="goal_marker", add_collision=False,
                body_type="kinematic", initial_pose=sapien.Pose(p=[10, 10, _PARK_Z]))

        def _initialize_episode(self, env_idx: torch.Tensor, options: dict):
            rng = self._episode_rng  # seeded by reset(seed=...): same seed, same scene
            with torch.device(self.device):
                self.table_scene.initialize(env_idx)
                names = list(OBJECTS)
                count = int(rng.randint(MIN_OBJECTS, MAX_OBJECTS + 1))
                chosen = [names[i] for i in sorted(rng.choice(len(names), size=count, replace=False))]
                xy = _sample_positions(rng, count + int(self.goal_marker))
                colors = rng.choice(list(PALETTE), size=count, replace=False)
                self.present = chosen
                self.object_colors = {n: str(c) for n, c in zip(chosen, colors)}
                upright = _quat_wxyz_about_y(-np.pi / 2)  # cylinder axis x -> z
                for i, name in enumerate(names):
                    shape, half_h = OBJECTS[name]
                    if name in chosen:
                        k = chosen.index(name)
                        yaw = _quat_wxyz_about_z(float(rng.uniform(-np.pi / 4, np.pi / 4)))
                        q = _quat_mul(yaw, upright) if shape == "cylinder" else yaw
                        p = [float(xy[k, 0]), float(xy[k, 1]), half_h]
                        _set_color(self.objects[name], COLORS[self.object_colors[name]])
                    else:
                        q, p = [1.0, 0.0, 0.0, 0.0], [10.0 + i, 0.0, _PARK_Z]
                    self.objects[name].set_pose(Pose.create_from_pq(p=torch.tensor([p]), q=torch.tensor([q])))
                if self.goal_marker:
                    m = xy[count]
                    q = _quat_wxyz_about_y(np.pi / 2)  # target disc lies flat on the table
                    self.goal_site.set_pose(Pose.create_from_pq(p=torch.tensor([[m[0], m[1], 1e-3]]),
                                                                q=torch.tensor([q])))

        def evaluate(self):
            return {"success": torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)}

        def _get_obs_extra(self, info: dict):
            return dict(tcp_pose=self.agent.tcp.pose.raw_pose)

        def compute_dense_reward(self, obs, action, info):
            return torch.zeros(self.num_envs, device=self.device)

        def compute_normalized_dense_reward(self, obs, action, info):
            return self.compute_dense_reward(obs, action, info)

    _registered = True
    return ENV_ID


def _sample_positions(rng, count: int, tries: int = 1000) -> np.ndarray:
    """``count`` points in REGION_XY at least MIN_SPACING_M apart (rejection sampling). (count, 2)."""
    (x0, x1), (y0, y1) = REGION_XY
    pts: list[np.ndarray] = []
    for _ in range(tries):
        p = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
        if all(np.linalg.norm(p - q) >= MIN_SPACING_M for q in pts):
            pts.append(p)
            if len(pts) == count:
                return np.stack(pts)
    raise RuntimeError(f"could not place {count} objects {MIN_SPACING_M} m apart in {REGION_XY}")


def _quat_wxyz_about_z(angle: float) -> list[float]:
    return [float(np.cos(angle / 2)), 0.0, 0.0, float(np.sin(angle / 2))]


def _quat_wxyz_about_y(angle: float) -> list[float]:
    return [float(np.cos(angle / 2)), 0.0, float(np.sin(angle / 2)), 0.0]


def _quat_mul(a, b) -> list[float]:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return [w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2]


def _set_color(actor, rgba) -> None:
    import sapien

    for obj in actor._objs:
        body = obj.find_component_by_type(sapien.render.RenderBodyComponent)
        for shape in body.render_shapes:
            for part in (shape.parts if hasattr(shape, "parts") and shape.parts else [shape]):
                part.material.base_color = list(rgba)
