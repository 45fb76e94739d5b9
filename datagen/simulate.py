"""Simulate one motion-planned episode and render the frames kept, as a dataset ``Episode``.

Speed: the motion planner drives an env with ``obs_mode="none"`` (no rendering per step,
~3 ms a step) while a wrapper records the action and the simulator state after every step.
Once the episode has succeeded, only the sub-sampled frames are rendered: for each kept step
the recorded state is set back (``set_state_dict``) and the cameras render it. Failed episodes
cost no rendering at all. The recorded actions re-simulate the episode exactly
(``Episode.env_kwargs`` / ``control_mode`` / ``seed``; see dataset_format.py).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from datagen.cameras import PRESETS, episode_views
from datagen.tasks import CONTROL_MODE, get_task
from tesseract4d.configs import knob
from tesseract4d.dataset_format import CameraFrames, Episode
from tesseract4d.errors import UserError
from datagen.capture import SceneRenderer
from datagen.tabletop import register
from datagen.instructions import make_instruction, scene_attributes

# Passed to gym.make; stored per episode so it can be re-simulated with the same settings.
# Random streams of an episode, seeded with [episode seed, stream]: independent of each other
# and of the planner's, so changing one never changes another.
APPEARANCE_STREAM, INSTRUCTION_STREAM = 104729, 31337
ENV_KWARGS = {"obs_mode": "none", "sim_backend": "physx_cpu", "render_backend": "cpu"}

VULKAN_FIX = (
    "SAPIEN found no working Vulkan driver. Run scripts/setup.sh (it installs the Mesa 25 lavapipe "
    "software driver into .deps/mesa), or point VK_ICD_FILENAMES at a working Vulkan ICD json."
)


@dataclass
class SimConfig:
    """How episodes are simulated and rendered (the datagen options that shape one episode)."""

    # training-data default; the tiny preset trains at 64 (datagen --resolution 64)
    height: int = knob(128, "image height in pixels (datagen --resolution sets both)")
    width: int = knob(128, "image width in pixels (datagen --resolution sets both)")
    cameras: list[str] = knob(help="camera presets (datagen/cameras.py)", default_factory=lambda: ["close"])
    frames: int = knob(16, "evenly spaced frames kept per episode, first and last included; 0 = every step")
    camera_jitter_m: float = knob(0.0, "move camera eye and target by up to this many metres per axis, per episode")
    randomize_colors: bool = knob(False, "random named colour of the task's cubes per episode (the instruction says "
                                         "it; the tabletop draws its objects' colours every episode anyway)")
    randomize_lighting: bool = knob(False, "random ambient/directional light per episode")
    instruction_split: str = knob("train", "instruction paraphrases to draw from ('heldout' is kept for evaluation)")
    goal_marker: bool = knob(False, "a red and white goal marker on the tabletop (default: none, so only the "
                                    "instruction says what should happen)")

    def env_kwargs(self, env_id: str) -> dict:
        """Keyword arguments of gym.make for ``env_id`` (stored per episode for re-simulation)."""
        extra = {"goal_marker": True} if self.goal_marker and get_task(env_id).skills_only else {}
        return dict(ENV_KWARGS, **extra)


@dataclass
class AttemptResult:
    """What one attempt of (task, seed) did; the episode itself only on success."""

    env_id: str
    seed: int
    success: bool
    num_steps: int = 0
    num_frames: int = 0
    plan_s: float = 0.0
    render_s: float = 0.0
    error: str = ""
    episode: Episode | None = None


def check_vulkan_env() -> None:
    """Fail early, with the fix, when VK_ICD_FILENAMES names a driver file that does not exist."""
    import os

    for var in ("VK_ICD_FILENAMES", "VK_DRIVER_FILES"):
        value = os.environ.get(var)
        if value:
            missing = [p for p in value.split(os.pathsep) if p and not os.path.isfile(p)]
            if missing:
                raise UserError(f"{var} names {', '.join(missing)}, which does not exist. {VULKAN_FIX}")


def package_versions() -> dict[str, str]:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("tesseract4d", "mani-skill", "sapien", "mplib", "numpy", "torch", "gymnasium"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def frame_indices(num_states: int, frames: int) -> np.ndarray:
    """Indices of ``frames`` evenly spaced states out of ``num_states`` (first and last included).

    frames <= 0 or >= num_states keeps them all. Returns (T,) int64, strictly increasing.
    """
    if frames <= 0 or frames >= num_states:
        return np.arange(num_states)
    return np.unique(np.linspace(0, num_states - 1, frames).round().astype(np.int64))


def _make_recorder():
    import gymnasium as gym

    class StateRecorder(gym.Wrapper):
        """Records the action and the full simulator state after reset and after every step."""

        def reset(self, **kwargs):
            out = super().reset(**kwargs)
            self.actions: list[np.ndarray] = []
            self.states: list[dict] = [self.env.unwrapped.get_state_dict()]
            return out

        def step(self, action):
            out = super().step(action)
            self.actions.append(np.asarray(action, dtype=np.float32).reshape(-1))
            self.states.append(self.env.unwrapped.get_state_dict())
            return out

    return StateRecorder


class EpisodeSimulator:
    """One task's env in this process, reused across seeds. Not thread-safe."""

    def __init__(self, env_id: str, config: SimConfig):
        self.spec = get_task(env_id)
        self.env_id = env_id
        self.config = config
        for cam in config.cameras:
            if cam not in PRESETS:
                raise UserError(f"unknown camera preset {cam!r}; choose from {', '.join(PRESETS)}")
        self._env = None
        self._renderer = None

    # ------------------------------------------------------------------ env

    @property
    def env(self):
        if self._env is None:
            self._env = self._make_env()
        return self._env

    def _make_env(self):
        check_vulkan_env()
        import gymnasium as gym
        import mani_skill.envs  # noqa: F401  (registers the tasks)

        register()  # the project's own scene

        try:
            env = gym.make(self.env_id, control_mode=CONTROL_MODE, render_mode=None, **self.config.env_kwargs(self.env_id))
        except RuntimeError as e:
            if any(word in str(e).lower() for word in ("vulkan", "vk::", "render", "physical device")):
                raise UserError(f"{VULKAN_FIX} ({e})") from e
            raise
        self._renderer = SceneRenderer(self.config.height, self.config.width)
        return _make_recorder()(env)

    def close(self) -> None:
        if self._env is not None:
            self._env.close()
            self._env = None

    # ------------------------------------------------------------------ episodes

    def fresh_scene(self, seed: int) -> None:
        """Rebuild the env's scene and reset it to ``seed``, so that what happens in the scene of
        ``seed`` does not depend on what this process simulated before. A plain ``reset(seed=...)``
        keeps ManiSkill's physics scene, and its contact state outlived it: a held-out tabletop
        group generated after another seed diverged at its first contact from the same group
        generated first (tests/datagen/test_skills.py). Costs about 0.1 s."""
        self.env.reset(seed=seed, options={"reconfigure": True})

    def run(self, seed: int) -> AttemptResult:
        """Plan the episode of ``seed``; on success render the kept frames into an Episode."""
        from mani_skill.examples.motionplanning.panda.run import MP_SOLUTIONS

        env = self.env
        self.fresh_scene(seed)
        t0 = time.perf_counter()
        try:
            res = MP_SOLUTIONS[self.env_id](env, seed=seed, debug=False, vis=False)
        except Exception as e:  # the planner raises on unreachable poses; that is a failed attempt
            return AttemptResult(self.env_id, seed, False, len(getattr(env, "actions", [])),
                                 plan_s=time.perf_counter() - t0, error=f"planner error: {type(e).__name__}: {e}")
        plan_s = time.perf_counter() - t0
        num_steps = len(env.actions)
        if res == -1 or not bool(np.asarray(res[-1]["success"]).reshape(-1)[0]):
            reason = "no motion plan found" if res == -1 else "task not solved"
            return AttemptResult(self.env_id, seed, False, num_steps, plan_s=plan_s, error=reason)
        t1 = time.perf_counter()
        keep = frame_indices(len(env.states), self.config.frames)
        episode = self._render(seed, [env.states[i] for i in keep], keep, np.stack(env.actions), success=True)
        episode.metadata.update({"num_sim_steps": num_steps, "plan_seconds": round(plan_s, 3)})
        return AttemptResult(self.env_id, seed, True, num_steps, len(keep), plan_s, time.perf_counter() - t1,
                             episode=episode)

    def first_frame(self, seed: int) -> Episode:
        """Reset to ``seed`` and render that one frame (no planning)."""
        env = self.env
        self.fresh_scene(seed)
        action_dim = int(np.prod(env.unwrapped.single_action_space.shape))
        return self._render(seed, [env.states[0]], np.zeros(1, np.int64), np.zeros((0, action_dim), np.float32),
                            success=None)

    def observe(self) -> dict:
        """Render the episode's cameras (placed by ``first_frame`` or ``run``) at the env's current
        state: camera name -> capture.Frame. Used by the closed-loop policy between actions."""
        return self._renderer.capture(self.env.unwrapped)

    def _set_up_scene(self, seed: int) -> tuple[list, dict]:
        """Place the (jittered) cameras and set colours and lighting for this seed."""
        cfg, spec, base = self.config, self.spec, self.env.unwrapped
        views = episode_views(cfg.cameras, self.env_id, seed, cfg.camera_jitter_m, base_env=base)
        self._renderer.set_views(base, views)
        colorable = {name: getattr(base, dict(spec.objects)[name]) for name in spec.colorable}
        appearance = self._renderer.set_appearance(base, colorable, np.random.default_rng([seed, APPEARANCE_STREAM]),
                                                   cfg.randomize_colors, cfg.randomize_lighting)
        return views, appearance

    def _capture(self, states: list[dict], views: list) -> tuple[dict[str, CameraFrames], np.ndarray, dict[str, np.ndarray]]:
        """Per camera, the frames of every state; the robot's joint positions (T, D) and each
        object's pose (T, 7) at those states."""
        base, renderer = self.env.unwrapped, self._renderer
        per_cam: dict[str, list] = {v.name: [] for v in views}
        actors = {name: getattr(base, attr) for name, attr in self.spec.objects}
        qpos, poses = [], {name: [] for name in actors}
        for state in states:
            base.set_state_dict(state)
            qpos.append(base.agent.robot.get_qpos()[0].cpu().numpy())
            for name, actor in actors.items():
                poses[name].append(actor.pose.raw_pose[0].cpu().numpy())
            for name, frame in renderer.capture(base).items():
                per_cam[name].append(frame)
        seg_names = renderer.segmentation_names(base)
        cameras = {
            name: CameraFrames(
                rgb=np.stack([f.rgb for f in fs]),  # (T, H, W, 3)
                depth_m=np.stack([f.depth_m for f in fs]),  # (T, H, W)
                normal_cam=np.stack([f.normal_cam for f in fs]),  # (T, H, W, 3)
                K=np.stack([f.K for f in fs]),  # (T, 3, 3)
                T_world_cam=np.stack([f.T_world_cam for f in fs]),  # (T, 4, 4)
                segmentation=np.stack([f.segmentation for f in fs]),  # (T, H, W)
                seg_id_to_name=seg_names,
            )
            for name, fs in per_cam.items()
        }
        object_poses = {name: np.stack(p).astype(np.float32) for name, p in poses.items()}  # (T, 7)
        return cameras, np.stack(qpos).astype(np.float32), object_poses

    def _instruction(self, seed: int, object_poses: dict[str, np.ndarray], colors: dict[str, str]) -> tuple[str, dict]:
        """The instruction for the scene at its first state, and the attributes it was made from."""
        attributes = scene_attributes(self.env_id, {n: p[0, :3] for n, p in object_poses.items()}, colors)
        instruction = make_instruction(self.env_id, attributes, np.random.default_rng([seed, INSTRUCTION_STREAM]),
                                       split=self.config.instruction_split)
        return instruction, attributes

    def _render(self, seed: int, states: list[dict], steps: np.ndarray, actions: np.ndarray, success,
                language=None, variant: int | None = None, intent: dict | None = None) -> Episode:
        """Replay the recorded states with the episode's cameras and appearance: RGB-D-N frames,
        robot and object poses, and the instruction for the scene.

        language: None = the task's own instruction templates; else a function
        (colour names of the colourable actors) -> (instruction, attributes), used by skill episodes.
        """
        cfg, spec = self.config, self.spec
        base = self.env.unwrapped
        base.set_state_dict(states[0])
        views, appearance = self._set_up_scene(seed)
        cameras, qpos, object_poses = self._capture(states, views)
        colors = {name: appearance["colors"].get(name, default)
                  for name, default in zip(spec.colorable, spec.default_colors)}
        if language is not None:
            instruction, attributes = language(colors)
        elif spec.skills_only:  # a scene without a task: the words come from a skill, or the user (predict)
            instruction, attributes = "", {"object_colors": dict(getattr(base, "object_colors", {}))}
        else:
            instruction, attributes = self._instruction(seed, object_poses, colors)
        control_freq = float(base.control_freq)
        span = int(steps[-1] - steps[0]) if len(steps) > 1 else 0
        fps = control_freq * (len(steps) - 1) / span if span else control_freq
        return Episode(
            env_id=self.env_id,
            seed=int(seed),
            instruction=instruction,
            cameras=cameras,
            frame_steps=np.asarray(steps, np.int32),
            actions=np.asarray(actions, np.float32),  # (S, A)
            qpos=qpos,  # (T, D)
            object_poses=object_poses,
            success=success,
            control_mode=CONTROL_MODE,
            env_kwargs=self.config.env_kwargs(self.env_id),
            fps=fps,
            variant=variant,
            intent=intent,
            metadata={
                "package_versions": package_versions(),
                "control_freq": control_freq,
                "instruction_split": cfg.instruction_split,
                "instruction_attributes": attributes,
                "camera_views": {v.name: {"eye": v.eye, "target": v.target, "up": v.up, "fov_deg": v.fov_deg}
                                 for v in views},
                "camera_jitter_m": cfg.camera_jitter_m,
                "appearance": appearance,
                "planner": "mani_skill.examples.motionplanning.panda MP_SOLUTIONS",
            },
        )


def first_frame_simulator(env_id: str, *, height: int = 64, width: int = 64, camera: str = "close",
                          instruction_split: str = "heldout") -> EpisodeSimulator:
    """A simulator that renders one frame per episode (no planning) with camera preset ``camera``
    (see cameras.PRESETS) or "all"; instructions from the ``instruction_split`` paraphrases.
    Close it when done."""
    cameras = list(PRESETS) if camera == "all" else [camera]
    return EpisodeSimulator(env_id, SimConfig(height=height, width=width, cameras=cameras, frames=1,
                                              instruction_split=instruction_split))


def render_first_frame(
    env_id: str, seed: int, *, height: int = 64, width: int = 64, camera: str = "close",
    instruction_split: str = "heldout",
) -> Episode:
    """Reset ``env_id`` with ``seed`` and render its first frame as a one-frame Episode.

    camera: a preset name (see cameras.PRESETS) or "all". The instruction is generated for this
    scene from the ``instruction_split`` paraphrases. Used by `tesseract4d predict`.
    """
    sim = first_frame_simulator(env_id, height=height, width=width, camera=camera, instruction_split=instruction_split)
    try:
        return sim.first_frame(seed)
    finally:
        sim.close()
