"""The policy loop: observe -> predict the clip -> reconstruct -> inverse dynamics -> act -> replan.

One episode in ManiSkill on the CPU:

1. observe: render the camera (RGB-D-N) at the current state;
2. predict: a 16-frame clip from the current frame and the instruction (``WorldModelFuture``), the
   true future of the motion planner's episode of the same seed (``OracleFuture``), or the current
   frame repeated (``StaticFuture``, the static world);
3. reconstruct: back-project the current and the next clip frame into world point clouds;
4. IDM: the action chunk between them and how many env steps it spans; execute it;
5. observe again and go to 3 with the next clip frame; every ``replan_every`` clip frames go to 2.

The world model, the IDM and the rendered camera may differ in resolution by a whole factor: the
observation goes to the world model's resolution and its prediction back (``tesseract4d.resize``,
edge-safe), and every frame reaches the IDM at the resolution it was trained on. So a 128² world
model steers an IDM trained on 64² renders of the same camera.

Behaviour cloning runs the same loop without steps 2 and the future cloud. Success is the env's own
``info["success"]``, reached at any step (ManiSkill's ``success_once``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from tesseract4d import dataset_format as df
from tesseract4d.configs import knob
from tesseract4d.errors import UserError
from tesseract4d.policy.idm import InverseDynamics, check_compatible, clip_gap, expand_chunk, sentence_embeddings
from tesseract4d.policy.points import frame_points
from tesseract4d.resize import resize_factor, resize_rgbdn
from tesseract4d.model.predict import predict_episode
from datagen.tasks import CONTROL_MODE

STAGES = ("observe", "predict", "reconstruct", "idm", "act")


@dataclass
class LoopConfig:
    # Clip frames executed per prediction (k). 15 = the whole clip, then a new prediction: measured
    # better with the shipped tiny model (trained only on clips that start an episode), whose clips
    # predicted from mid-episode frames degrade: world-model arm 3/10 at k = 15 vs 0/10 at k = 4
    # on PushCube + PullCube, 5 held-out seeds each.
    replan_every: int = knob(15, "predicted frames executed per prediction (k, below the clip's length)")
    max_steps: int = knob(200, "simulator steps before the episode counts as failed (rollout --max-sim-steps)")
    max_chunk_steps: int = knob(30, "upper bound on the simulator steps one IDM chunk may span")
    num_frames: int = knob(16, "frames per predicted clip")
    sample_steps: int | None = knob(None, "sampler steps per prediction (rollout --steps; none: the checkpoint's)")
    draws: int | None = knob(None, "noise draws per prediction, the one whose objects keep their colours best kept "
                                   "(none: the checkpoint's)")
    sample_seed: int = knob(0, "noise seed of the world model")
    camera: str = knob("close", "camera preset of the rendered observation")
    resolution: tuple[int, int] = knob((64, 64), "rendered observation (height, width); rollout: the world "
                                                 "model's with the world_model arm, else the IDM's")
    instruction_split: str = knob("heldout", "instruction paraphrases (train or heldout)", choices=("train", "heldout"))
    point_seed: int = knob(0, "seed of the IDM's point sampling")
    plan_replans: int = knob(3, "plan arms: primitives (each after a new prediction) before the episode ends")


@dataclass
class FutureClip:
    """Frames 0..T-1 of a future starting at the current observation (frame 0)."""

    rgb: np.ndarray  # (T, H, W, 3) uint8
    depth_m: np.ndarray  # (T, H, W)
    K: np.ndarray  # (T, 3, 3)
    T_world_cam: np.ndarray  # (T, 4, 4)
    episode: df.Episode | None = None  # the prediction as a dataset episode (viewer)


class StageClock:
    """Seconds per stage of an episode: ``lap(stage)`` charges the time since the last lap to ``stage``."""

    def __init__(self, stages) -> None:
        self.seconds = dict.fromkeys(stages, 0.0)
        self.start = self._tick = time.perf_counter()

    def lap(self, stage: str) -> None:
        now = time.perf_counter()
        self.seconds[stage] += now - self._tick
        self._tick = now


@dataclass
class EpisodeResult:
    env_id: str
    seed: int
    arm: str
    success: bool
    success_at_end: bool
    steps: int
    replans: int
    chunks: int
    seconds: float
    stage_seconds: dict = field(default_factory=dict)
    instruction: str = ""
    error: str = ""
    plan: list = field(default_factory=list)  # plan arms: per replan the goal read and the primitive run


@dataclass
class Trace:
    """What the robot saw and what it was steering toward, per executed chunk (for MP4s and the viewer)."""

    observed: list = field(default_factory=list)  # capture.Frame after each chunk (index 0 = start)
    targets: list = field(default_factory=list)  # (H, W, 3) uint8 target frame per chunk, or None
    replans: list = field(default_factory=list)  # (first observed index, FutureClip) per replan


def at_hw(rgb: np.ndarray, depth_m: np.ndarray, normal_cam: np.ndarray | None, K: np.ndarray,
          hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(rgb, depth_m, normal_cam, K) of a frame or clip at ``hw`` (a whole factor up or down; the
    same arrays when already there). ``normal_cam`` None: no normals (None, or zeros when resized)."""
    if tuple(depth_m.shape[-2:]) == tuple(hw):
        return rgb, depth_m, normal_cam, K
    normal = np.zeros(rgb.shape, np.float32) if normal_cam is None else normal_cam
    return resize_rgbdn(rgb, depth_m, normal, K, *hw)


def idm_points(config, rgb: np.ndarray, depth_m: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray,
               rng: np.random.Generator) -> np.ndarray:
    """The IDM's point cloud of one frame, taken at the resolution the IDM (``config``) was trained on."""
    rgb, depth_m, _, K = at_hw(rgb, depth_m, None, K, tuple(config.resolution))
    return frame_points(rgb, depth_m, K, T_world_cam, config.num_points, rng)


def observation_episode(frames: list, env_id: str, seed: int, instruction: str, camera: str) -> df.Episode:
    """Observed capture.Frames as a dataset episode (viewer / world-model input)."""
    cam = df.CameraFrames(
        rgb=np.stack([f.rgb for f in frames]), depth_m=np.stack([f.depth_m for f in frames]).astype(np.float32),
        normal_cam=np.stack([f.normal_cam for f in frames]).astype(np.float32), K=np.stack([f.K for f in frames]),
        T_world_cam=np.stack([f.T_world_cam for f in frames]),
    )
    return df.Episode(env_id=env_id, seed=int(seed), instruction=instruction, cameras={camera: cam},
                      frame_steps=np.arange(len(frames), dtype=np.int32), source="rollout observation")


class WorldModelFuture:
    """The world model's clip from the current frame and the instruction."""

    name = "world_model"

    def __init__(self, pipeline, config: LoopConfig):
        self.pipeline = pipeline
        self.config = config
        ckpt_cam = pipeline.camera_name
        self.model_hw = tuple(pipeline.resolution)
        if resize_factor(config.resolution, self.model_hw) is None or (ckpt_cam and ckpt_cam != config.camera):
            raise UserError(f"the world model was trained on camera {ckpt_cam!r} at {self.model_hw[0]}x{self.model_hw[1]} "
                            f"but the rollout renders camera {config.camera!r} at {config.resolution[0]}x{config.resolution[1]}; "
                            f"pass --camera {ckpt_cam} --resolution {self.model_hw[0]} (or a whole multiple or divisor of "
                            f"it) or use a matching checkpoint")

    def clip(self, frame, env_id: str, seed: int, instruction: str, step: int) -> FutureClip:
        c = self.config
        first = observation_episode([frame], env_id, seed, instruction, c.camera)
        cam = first.cameras[c.camera]
        cam.rgb, cam.depth_m, cam.normal_cam, cam.K = at_hw(cam.rgb, cam.depth_m, cam.normal_cam, cam.K, self.model_hw)
        pred = predict_episode(self.pipeline, first, instruction, num_frames=c.num_frames, num_steps=c.sample_steps,
                               seed=c.sample_seed + step, draws=c.draws)
        cam = pred.cameras[c.camera]
        # back at the rendered resolution; frame 0 is the observation itself
        cam.rgb, cam.depth_m, cam.normal_cam, cam.K = at_hw(cam.rgb, cam.depth_m, cam.normal_cam, cam.K,
                                                            tuple(c.resolution))
        cam.rgb[0], cam.depth_m[0], cam.normal_cam[0] = frame.rgb, frame.depth_m, frame.normal_cam
        return FutureClip(cam.rgb, cam.depth_m, cam.K, cam.T_world_cam, episode=pred)


class OracleFuture:
    """The true future: the motion planner's episode of the same seed (rendered every step),
    sampled from the current step every G steps (G = planner steps / 15, as in training)."""

    name = "oracle_future"

    def __init__(self, planner_episode: df.Episode, config: LoopConfig):
        self.episode = planner_episode
        self.config = config
        self.cam = planner_episode.cameras[config.camera]
        steps = len(planner_episode.actions)
        self.gap = clip_gap(steps)  # the spacing of the IDM's training pairs
        if not np.array_equal(planner_episode.frame_steps, np.arange(steps + 1)):
            raise UserError("the oracle future needs the planner episode rendered at every step (frames=0)")

    def clip(self, frame, env_id: str, seed: int, instruction: str, step: int) -> FutureClip:
        last = len(self.cam.rgb) - 1
        idx = np.minimum(step + self.gap * np.arange(self.config.num_frames), last)
        c = self.cam
        return FutureClip(c.rgb[idx], c.depth_m[idx], c.K[idx], c.T_world_cam[idx])


class StaticFuture:
    """The static world: the current observation repeated as every frame of the clip, i.e. a world
    model that predicts no motion. The IDM fed it acts on the observation and the instruction alone,
    so its arm measures how much of the world-model arm's success the predicted frames bring."""

    name = "static_world"

    def __init__(self, config: LoopConfig):
        self.config = config

    def clip(self, frame, env_id: str, seed: int, instruction: str, step: int) -> FutureClip:
        n = self.config.num_frames

        def repeat(a):
            return np.repeat(np.asarray(a)[None], n, axis=0)

        return FutureClip(repeat(frame.rgb), repeat(frame.depth_m), repeat(frame.K), repeat(frame.T_world_cam))


class PolicyRunner:
    """Runs episodes of one arm ("oracle_future", "world_model", "static_world" or "behavior_cloning") in
    one env."""

    def __init__(self, simulator, model: InverseDynamics, text_encoder, config: LoopConfig):
        self.sim = simulator
        self.model = model
        self.text_encoder = text_encoder
        self.config = config
        if (config.replan_every < 1 or config.replan_every >= config.num_frames) and model.config.use_future:
            raise UserError(f"--replan-every must be between 1 and {config.num_frames - 1} clip frames")

    def check_env(self) -> None:
        env = self.sim.env

        action_dim = int(np.prod(env.unwrapped.single_action_space.shape))
        check_compatible(self.model.config, control_mode=CONTROL_MODE, action_dim=action_dim, camera=self.config.camera,
                         resolution=tuple(self.config.resolution), what=f"the rollout env {self.sim.env_id}")

    @torch.no_grad()
    def run(self, seed: int, future=None, trace: Trace | None = None, instruction: str | None = None,
            success_check=None) -> EpisodeResult:
        """One episode of ``seed``. instruction: None = the task's own; success_check: None = the env's own
        success signal after every step, else a function called once after reset (it reads the start)
        returning one that says whether the task is done now, asked after every chunk (a tabletop skill:
        ``tesseract4d.policy.tabletop_tasks.success_check``)."""
        c, model = self.config, self.model
        arm = future.name if future is not None else "behavior_cloning"
        if model.config.use_future != (future is not None):
            raise UserError(f"arm {arm} needs an IDM with use_future={future is not None}; this one has "
                            f"use_future={model.config.use_future}")
        self.check_env()
        clock = StageClock(STAGES)
        timings, t_start, lap = clock.seconds, clock.start, clock.lap

        first = self.sim.first_frame(seed)
        instruction = first.instruction if instruction is None else instruction
        done = success_check() if success_check is not None else None
        frame = self.sim.observe()[c.camera]
        lap("observe")
        text = sentence_embeddings(self.text_encoder, [instruction])  # (1, d)
        rng = np.random.default_rng([c.point_seed, seed])
        env = self.sim.env
        success = success_now = False
        steps = replans = chunks = 0
        if trace is not None:
            trace.observed.append(frame)
            trace.targets.append(None)
        while steps < c.max_steps and not success:
            clip = None
            if future is not None:
                clip = future.clip(frame, self.sim.env_id, seed, instruction, steps)
                replans += 1
                if trace is not None:
                    trace.replans.append((len(trace.observed) - 1, clip))
                lap("predict")
            targets = range(1, c.replan_every + 1) if clip is not None else range(1)
            for j in targets:
                now_pts = idm_points(model.config, frame.rgb, frame.depth_m, frame.K, frame.T_world_cam, rng)
                next_pts = None
                if clip is not None:
                    next_pts = torch.from_numpy(idm_points(model.config, clip.rgb[j], clip.depth_m[j], clip.K[j],
                                                           clip.T_world_cam[j], rng))[None]
                lap("reconstruct")
                qpos = torch.from_numpy(self.sim.env.unwrapped.agent.robot.get_qpos()[0].cpu().numpy().astype(np.float32))[None]
                out = model(torch.from_numpy(now_pts)[None], next_pts, text, qpos)
                chunk, n = model.decode(out, qpos)
                n_steps = int(np.clip(round(float(n[0])), 1, c.max_chunk_steps))
                actions = expand_chunk(chunk[0].numpy(), n_steps)  # (n_steps, A)
                lap("idm")
                for a in actions:
                    _, _, _, _, info = env.step(a)
                    steps += 1
                    if done is None:
                        success_now = bool(np.asarray(info["success"]).reshape(-1)[0])
                        success |= success_now
                    if success or steps >= c.max_steps:
                        break
                if done is not None:
                    success_now = done()
                    success |= success_now
                chunks += 1
                lap("act")
                frame = self.sim.observe()[c.camera]
                lap("observe")
                if trace is not None:
                    trace.observed.append(frame)
                    trace.targets.append(clip.rgb[j] if clip is not None else None)
                if success or steps >= c.max_steps:
                    break
        return EpisodeResult(self.sim.env_id, int(seed), arm, success, success_now, steps, replans, chunks,
                             time.perf_counter() - t_start, {k: round(v, 3) for k, v in timings.items()}, instruction)
