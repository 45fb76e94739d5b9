"""Render RGB-D-N(-segmentation) frames of a ManiSkill scene from datagen's own cameras.

The simulation env runs with ``obs_mode="none"`` (no rendering per step); ``SceneRenderer``
adds SAPIEN cameras with the ``default`` shader pack (the one with normals) to the env's scene
and renders them only when asked. It converts SAPIEN's outputs once, here, with
``tesseract4d.conventions``: int16 millimetre depth -> ``depth_m``, OpenGL-frame normals ->
``normal_cam`` (OpenCV frame), ``cam2world_gl`` -> ``T_world_cam``.

It also owns the scene's appearance randomisation (object colours, lighting): render-only
changes that do not touch physics, so actions replay identically.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datagen.cameras import CameraView
from datagen.palette import COLORS
from tesseract4d.conventions import T_world_cam_from_cam2world_gl, depth_m_from_mm, normal_gl_to_cv

SHADER_PACK = "default"  # the only prebuilt pack that renders normals
CAMERA_UID_PREFIX = "t4d_"


@dataclass
class Frame:
    """One camera's picture. H x W pixels."""

    rgb: np.ndarray  # (H, W, 3) uint8
    depth_m: np.ndarray  # (H, W) float32, metres along OpenCV +z, 0 = no hit
    normal_cam: np.ndarray  # (H, W, 3) float32, unit, OpenCV camera frame, 0 = no hit
    segmentation: np.ndarray  # (H, W) int32 per-scene actor/link id, 0 = background
    K: np.ndarray  # (3, 3) float64
    T_world_cam: np.ndarray  # (4, 4) float64


class SceneRenderer:
    """Datagen's cameras in one env's scene; re-creates them when the env rebuilds its scene."""

    def __init__(self, height: int, width: int):
        self.height, self.width = int(height), int(width)
        self._scene = None
        self._cameras: dict[str, object] = {}  # preset name -> mani_skill Camera
        self._fov: dict[str, float] = {}
        self._default_appearance: dict | None = None

    # ------------------------------------------------------------------ cameras

    def _track_scene(self, base_env) -> None:
        # ManiSkill builds a new scene object on reconfigure (e.g. PegInsertionSide every reset):
        # cameras and remembered default colours belong to the old one.
        if base_env.scene is not self._scene:
            self._scene = base_env.scene
            self._cameras, self._fov = {}, {}
            self._default_appearance = None

    def set_views(self, base_env, views: list[CameraView]) -> None:
        """Place one camera per view (creating it the first time in this scene)."""
        from mani_skill.sensors.camera import Camera, CameraConfig
        from mani_skill.utils.sapien_utils import look_at

        self._track_scene(base_env)
        wanted = {v.name for v in views}
        for name in [n for n in self._cameras if n not in wanted]:
            del self._cameras[name]
        for view in views:
            pose = look_at(list(view.eye), list(view.target), up=list(view.up))
            cam = self._cameras.get(view.name)
            if cam is None or self._fov[view.name] != view.fov_deg:
                config = CameraConfig(
                    uid=CAMERA_UID_PREFIX + view.name, pose=pose, width=self.width, height=self.height,
                    fov=float(np.radians(view.fov_deg)), near=view.near, far=view.far, shader_pack=SHADER_PACK,
                )
                self._cameras[view.name] = Camera(config, base_env.scene)
                self._fov[view.name] = view.fov_deg
            else:
                cam.camera.set_local_pose(pose.sp)

    def capture(self, base_env) -> dict[str, Frame]:
        """Render every camera at the scene's current state."""
        for obj in base_env._hidden_objects:  # what ManiSkill hides from its own sensors (e.g. PickCube's goal)
            obj.hide_visual()
        base_env.scene.update_render(update_sensors=True, update_human_render_cameras=False)
        for cam in self._cameras.values():
            cam.capture()
        frames = {}
        for name, cam in self._cameras.items():
            obs = cam.get_obs(rgb=True, depth=True, position=False, segmentation=True, normal=True)
            params = cam.get_params()
            frames[name] = Frame(
                rgb=obs["rgb"][0].cpu().numpy().astype(np.uint8),
                depth_m=depth_m_from_mm(obs["depth"][0, ..., 0].cpu().numpy()),
                normal_cam=normal_gl_to_cv(obs["normal"][0].cpu().numpy()),
                segmentation=obs["segmentation"][0, ..., 0].cpu().numpy().astype(np.int32),
                K=params["intrinsic_cv"][0].cpu().numpy().astype(np.float64),
                T_world_cam=T_world_cam_from_cam2world_gl(params["cam2world_gl"][0].cpu().numpy()),
            )
        return frames

    @staticmethod
    def segmentation_names(base_env) -> dict[int, str]:
        """Per-scene segmentation id -> actor/link name; 0 is the background."""
        names = {0: "background"}
        names.update({int(i): obj.name for i, obj in base_env.segmentation_id_map.items()})
        return names

    # ------------------------------------------------------------------ appearance

    def set_appearance(
        self, base_env, colorable: dict, rng: np.random.Generator,
        randomize_colors: bool, randomize_lighting: bool,
    ) -> dict:
        """Recolour the ``colorable`` actors (recorded name -> ManiSkill Actor) and/or change the lights, or restore ManiSkill's defaults.

        Returns what was applied (JSON-able): {"colors": {actor: colour name}, "lighting": {...}}.
        Colours are distinct named colours from palette.COLORS, so instructions can say them.
        """
        self._track_scene(base_env)
        if self._default_appearance is None:
            self._default_appearance = self._read_appearance(base_env, colorable)
        default = self._default_appearance
        applied: dict = {"colors": {}, "lighting": {}}
        if randomize_colors and colorable:
            names = rng.choice(sorted(COLORS), size=len(colorable), replace=False)
            for (name, actor), color_name in zip(colorable.items(), names):
                self._set_actor_color(actor, COLORS[str(color_name)])
                applied["colors"][name] = str(color_name)
        else:
            for name, actor in colorable.items():
                self._set_actor_color(actor, default["colors"][name])
        render_scene = base_env.scene.sub_scenes[0].render_system
        lights = self._lights(base_env)
        if randomize_lighting:
            ambient = float(rng.uniform(0.1, 0.5))
            tint = rng.uniform(0.9, 1.1, 3)
            render_scene.ambient_light = (ambient * tint).tolist()
            scales = []
            for light, base in zip(lights, default["lights"]):
                scale = float(rng.uniform(0.4, 1.4))
                light.color = (np.asarray(base) * scale * rng.uniform(0.9, 1.1, 3)).tolist()
                scales.append(scale)
            applied["lighting"] = {"ambient": ambient, "light_scales": scales}
        else:
            render_scene.ambient_light = default["ambient"]
            for light, base in zip(lights, default["lights"]):
                light.color = base
        return applied

    @staticmethod
    def _shapes(actor):
        import sapien

        for obj in actor._objs:
            body = obj.find_component_by_type(sapien.render.RenderBodyComponent)
            for shape in body.render_shapes:
                yield from (shape.parts if hasattr(shape, "parts") and shape.parts else [shape])

    def _set_actor_color(self, actor, rgba) -> None:
        for shape in self._shapes(actor):
            shape.material.base_color = list(rgba)

    @staticmethod
    def _lights(base_env) -> list:
        out = []
        for entity in base_env.scene.sub_scenes[0].entities:
            for comp in entity.components:
                if "Light" in type(comp).__name__ and hasattr(comp, "color"):
                    out.append(comp)
        return out

    def _read_appearance(self, base_env, colorable: dict) -> dict:
        colors = {}
        for name, actor in colorable.items():
            shapes = list(self._shapes(actor))
            colors[name] = list(shapes[0].material.base_color) if shapes else [1.0, 1.0, 1.0, 1.0]
        return {
            "colors": colors,
            "ambient": list(base_env.scene.sub_scenes[0].render_system.ambient_light),
            "lights": [list(light.color) for light in self._lights(base_env)],
        }
