"""Predict, then plan: a closed loop that reads the goal from a future's objects and executes a
motion-planned primitive toward it.

One episode in ManiSkill, per replan:

1. observe: render the camera (RGB-D-N + segmentation) and perceive every object's pose in it
   (:mod:`tesseract4d.policy.perception`; never the simulator's state);
2. predict: the world model's clip from the observation and the instruction (``world_model_plan``),
   or the true future of the motion planner's episode of the seed (``oracle_plan``); the
   ``words_plan`` arm parses the instruction instead (:mod:`tesseract4d.policy.words`);
3. reconstruct: the clip's object layer (:func:`reconstruction.objects.track_objects`, the objects named
   by the observation's segmentation) with the hand's track it read (``layer.hand``, :mod:`reconstruction.hand_track`);
4. plan: read the goal (:func:`tesseract4d.policy.goal_reading.read_goal`): which object moves, where
   to, lifted or set on another (from the arm's motion where the clip lost the object it moves); its
   target = the perceived centre + the predicted displacement;
5. execute: the primitive toward it (:mod:`tesseract4d.policy.primitives`), then go to 1.

The loop stops when the future says the goal is reached (no object moves in the prediction; for the
oracle and the words, whose goal is fixed at the start, when the perceived object is within
``REACHED_M`` of it), after ``plan_replans`` primitives, when the step budget is spent, or on success.
Success is the env's own ``info["success"]`` at any step for the ManiSkill tasks; for the tabletop's
skills (no task success) the skill library's ``check_intent`` on the simulator's object poses after
each primitive — both read by the evaluation, never by the arm.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from reconstruction.objects import TRACKED, first_frame_masks, instructed_object, track_objects
from tesseract4d.geometry import invert_pose, project_points, transform_points
from tesseract4d.policy.goal_reading import read_goal
from tesseract4d.policy.loop import EpisodeResult, FutureClip, StageClock, Trace, WorldModelFuture
from tesseract4d.policy.perception import ObjectPerception, PerceivedObject
from tesseract4d.policy.primitives import PrimitiveFailure, run_primitive
from tesseract4d.policy.words import parse_instruction

PLAN_ARMS = ("world_model_plan", "oracle_plan", "words_plan")
PLAN_STAGES = ("observe", "predict", "reconstruct", "plan", "execute", "simulate")
REACHED_M = 0.02  # a fixed goal counts as reached when the object's centre is this close to it
REFIT_RMS_M = 0.006  # a last-frame refit by colour counts when its points lie this close to the model
VIDEO_EVERY_STEPS = 4  # the MP4's observed frames: one every this many simulator steps


@dataclass
class PlanStep:
    """One primitive the arm chose: what it read and what it did (world metres)."""

    skill: str  # push | pull | pick_place | lift | stack | none
    target: str | None = None
    target_centre_m: list | None = None
    on: str | None = None
    reading: dict = field(default_factory=dict)  # the goal reading or the parse it came from
    error: str = ""


class OutOfSteps(Exception):
    """The episode's step budget is spent."""


def _watch(env, max_steps: int, on_step):
    """``env`` wrapped so every step is counted and reported to ``on_step(info)``; OutOfSteps once the
    budget is spent (the motion planner steps the env itself)."""
    import gymnasium as gym

    class Watch(gym.Wrapper):
        steps = 0
        sim_s = 0.0

        def step(self, action):
            if Watch.steps >= max_steps:
                raise OutOfSteps
            t0 = time.perf_counter()
            out = super().step(action)
            Watch.sim_s += time.perf_counter() - t0
            Watch.steps += 1
            on_step(out[-1])
            return out

    return Watch(env), Watch


def draw_target(rgb: np.ndarray, centre_world_m, K: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """A copy of ``rgb`` (H, W, 3) with the world point ``centre_world_m`` (3,) drawn as a magenta ring
    and cross (nothing drawn when it is behind the camera)."""
    import cv2  # OpenCV loads with the drawing only


    out = np.ascontiguousarray(rgb).copy()
    if centre_world_m is None:
        return out
    p_cam = transform_points(invert_pose(T_world_cam), np.asarray(centre_world_m, np.float64)[None])
    uv, z = project_points(p_cam, K)
    if not np.isfinite(uv).all() or z[0] <= 0:
        return out
    u, v = int(round(float(uv[0, 0]))), int(round(float(uv[0, 1])))
    r = max(2, out.shape[0] // 32)
    cv2.circle(out, (u, v), r, (255, 0, 255), 1, cv2.LINE_AA)
    cv2.line(out, (u - r, v), (u + r, v), (255, 0, 255), 1)
    cv2.line(out, (u, v - r), (u, v + r), (255, 0, 255), 1)
    return out


def clip_object_layer(clip: FutureClip, normal_cam: np.ndarray, frame0, seg_id_to_name: dict, instruction: str,
                      perception: ObjectPerception | None = None):
    """The object layer of ``clip`` (frame 0 = the observation ``frame0``), its objects named by the
    observation's segmentation; the instructed one found by its colour word (the first one named when the
    words name several). ``perception``: an
    ObjectPerception of ``frame0`` that re-finds objects lost at the end."""
    masks, source = first_frame_masks(frame0.rgb, frame0.segmentation, seg_id_to_name)
    depth = np.asarray(clip.depth_m, np.float32)
    layer = track_objects(clip.rgb, depth, normal_cam, clip.K, clip.T_world_cam, masks, source)
    # Frames where the tracker lost an object, saw it covered or carried it — a 16-frame clip moves a pushed
    # or carried cube several centimetres a frame, faster than the tracker follows — are fitted once more:
    # the object found by its own colours in that frame (the perception's fit, the model of the same first
    # frame).
    if perception is not None:
        for tr in layer.tracks:
            redo = [t for t in range(1, len(depth)) if tr.state[t] != TRACKED]
            if redo:
                tr.T_world_object, tr.state = tr.T_world_object.copy(), tr.state.copy()
            for t in redo:
                fit = perception.fit_by_colour(tr.name, clip.rgb[t], depth[t], normal_cam[t], clip.K[t], clip.T_world_cam[t])
                if fit is not None and fit[1] < REFIT_RMS_M:
                    tr.T_world_object[t] = fit[0]
                    tr.state[t] = TRACKED
    layer.instructed = instructed_object(layer.names(), [t.colour_name for t in layer.tracks], None, instruction)
    if layer.instructed is None:  # several colours named ("the red box onto the green box"): the first one's
        colour = parse_instruction(instruction).object_colour
        hits = [t.name for t in layer.tracks if colour and t.colour_name == colour]
        layer.instructed = hits[0] if len(hits) == 1 else None
    return layer


def _absolute(goal, objects: dict[str, PerceivedObject]) -> PlanStep:
    """A goal read from a future starting now -> a primitive toward an absolute target."""
    if goal.skill == "none" or goal.target not in objects:
        return PlanStep("none", goal.target, reading=goal.as_dict())
    centre = objects[goal.target].centre_world_m + goal.displacement_m
    if goal.skill in ("push", "pull", "pick_place"):
        centre[2] = objects[goal.target].centre_world_m[2]  # it ends on the table
    return PlanStep(goal.skill, goal.target, [float(v) for v in centre], goal.on, goal.as_dict())


def reached(step: PlanStep, objects: dict[str, PerceivedObject]) -> bool:
    """Whether the perceived objects already show ``step``'s goal."""
    if step.skill == "none" or step.target not in objects:
        return True
    obj = objects[step.target]
    if step.skill == "stack":
        other = objects.get(step.on)
        if other is None:
            return False
        gap = obj.centre_world_m - other.centre_world_m
        return bool(np.linalg.norm(gap[:2]) < REACHED_M and abs(gap[2] - obj.half_height_m - other.half_height_m) < 0.01)
    d = obj.centre_world_m - np.asarray(step.target_centre_m)
    return bool(np.linalg.norm(d if step.skill == "lift" else d[:2]) < REACHED_M)


class WorldModelPlan:
    """Goals read from the world model's clip predicted from each observation."""

    name = "world_model_plan"

    def __init__(self, pipeline, config):
        self.future = WorldModelFuture(pipeline, config)
        self.camera = config.camera
        self.env_id, self.seed = "", 0  # of the episode (set by the rollout), written into the prediction

    def plan(self, frame, objects, seg_id_to_name, instruction, step, lap) -> tuple[PlanStep, FutureClip | None]:
        clip = self.future.clip(frame, self.env_id, self.seed, instruction, step)
        lap("predict")
        normals = clip.episode.cameras[self.camera].normal_cam
        layer = clip_object_layer(clip, normals, frame, seg_id_to_name, instruction, ObjectPerception(frame, seg_id_to_name))
        lap("reconstruct")
        return _absolute(read_goal(layer, gripper=layer.hand), objects), clip


class OraclePlan:
    """The goal read, once, from the true future (the motion planner's episode of the seed, its
    ``num_frames`` evenly spaced frames) through the same reconstruction and reading."""

    name = "oracle_plan"

    def __init__(self, planner_episode, config):
        cam = planner_episode.cameras[config.camera]
        idx = np.unique(np.linspace(0, cam.num_frames - 1, config.num_frames).round().astype(int))
        self.clip = FutureClip(cam.rgb[idx], cam.depth_m[idx], cam.K[idx], cam.T_world_cam[idx])
        self.normals = cam.normal_cam[idx]
        self.goal: PlanStep | None = None

    def plan(self, frame, objects, seg_id_to_name, instruction, step, lap) -> tuple[PlanStep, FutureClip | None]:
        if self.goal is None:
            layer = clip_object_layer(self.clip, self.normals, frame, seg_id_to_name, instruction,
                                      ObjectPerception(frame, seg_id_to_name))
            lap("reconstruct")
            self.goal = _absolute(read_goal(layer, gripper=layer.hand), objects)
            return self.goal, self.clip
        return (PlanStep("none", self.goal.target, reading={"reached": True}) if reached(self.goal, objects)
                else self.goal), None


class WordsPlan:
    """The goal from the instruction's words alone (rules; no world model), fixed at the start."""

    name = "words_plan"

    def __init__(self):
        self.goal: PlanStep | None = None

    def plan(self, frame, objects, seg_id_to_name, instruction, step, lap) -> tuple[PlanStep, FutureClip | None]:
        if self.goal is None:
            self.goal = words_goal(instruction, objects)
            return self.goal, None
        return (PlanStep("none", self.goal.target, reading={"reached": True}) if reached(self.goal, objects)
                else self.goal), None


def _by_colour(colour: str | None, shape: str | None, objects: dict[str, PerceivedObject]) -> str | None:
    """The perceived object a colour word names (the only object when the scene has one)."""
    if len(objects) == 1:
        return next(iter(objects))
    hits = [n for n, o in objects.items() if colour and o.colour_name == colour]
    return hits[0] if len(hits) == 1 else None


def words_goal(instruction: str, objects: dict[str, PerceivedObject]) -> PlanStep:
    """The primitive the words ask for, toward an absolute target from the perceived poses."""

    p = parse_instruction(instruction)
    reading = {"parsed_skill": p.skill, "object": p.object_colour, "other": p.other_colour,
               "direction_xy": p.direction_xy, "distance_m": p.distance_m}
    if p.skill not in ("push", "pull", "pick_place", "lift", "stack"):
        return PlanStep("none", reading=reading, error=f"the words ask for no object motion the primitives make ({p.skill})")
    target = _by_colour(p.object_colour, p.object_shape, objects)
    if target is None:
        return PlanStep("none", reading=reading, error=f"no perceived object is {p.object_colour!r}")
    centre = objects[target].centre_world_m.copy()
    if p.skill == "stack":
        others = {n: o for n, o in objects.items() if n != target}
        on = _by_colour(p.other_colour, p.other_shape, others)
        if on is None:
            return PlanStep("none", target, reading=reading, error=f"no perceived object is {p.other_colour!r}")
        goal = objects[on].centre_world_m + [0, 0, objects[on].half_height_m + objects[target].half_height_m]
        return PlanStep("stack", target, [float(v) for v in goal], on, reading)
    if p.skill == "lift":
        centre[2] += p.travel_m()
        return PlanStep("lift", target, [float(v) for v in centre], reading=reading)
    d = np.asarray(p.direction_xy or (1.0, 0.0))
    centre[:2] += d * p.travel_m()
    return PlanStep(p.skill, target, [float(v) for v in centre], reading=reading)


class PlanRunner:
    """Runs episodes of one plan arm in one simulator (``datagen.simulate.EpisodeSimulator``).

    success_check: None for a ManiSkill task (the env's own success at any step), else a function called
    once after the reset that returns the evaluation's check of the tabletop skill, called after each
    primitive (``tesseract4d.policy.tabletop_tasks.success_check``). instruction: None = the task's own."""

    def __init__(self, simulator, config):
        self.sim = simulator
        self.config = config

    def run(self, seed: int, source, instruction: str | None = None, success_check=None,
            trace: Trace | None = None) -> EpisodeResult:

        c = self.config
        clock = StageClock(PLAN_STAGES)
        timings, t_start, lap = clock.seconds, clock.start, clock.lap

        first = self.sim.first_frame(seed)
        instruction = first.instruction if instruction is None else instruction
        seg_names = first.cameras[c.camera].seg_id_to_name
        success_after = success_check() if success_check is not None else None
        frame = self.sim.observe()[c.camera]
        perception = ObjectPerception(frame, seg_names)
        objects = perception.last
        lap("observe")
        state = {"success": False, "now": False}
        shown = {"target": None}

        def on_step(info):
            if success_after is None:
                state["now"] = bool(np.asarray(info["success"]).reshape(-1)[0])
                state["success"] |= state["now"]
            if trace is not None and watch_cls.steps % VIDEO_EVERY_STEPS == 0:
                f = self.sim.observe()[c.camera]
                trace.observed.append(f)
                trace.targets.append(shown["target"](len(trace.observed)) if shown["target"] else None)

        env, watch_cls = _watch(self.sim.env, c.max_steps, on_step)
        if trace is not None:
            trace.observed.append(frame)
            trace.targets.append(None)
        steps_taken: list[PlanStep] = []
        error = ""
        replans = 0
        while replans < c.plan_replans and not state["success"]:
            step, clip = source.plan(frame, objects, seg_names, instruction, watch_cls.steps, lap)
            lap("plan")
            replans += 1
            steps_taken.append(step)
            if trace is not None:
                shown["target"] = _target_images(clip, frame, step, len(trace.observed))
                if clip is not None:
                    trace.replans.append((len(trace.observed) - 1, clip))
            if step.skill == "none":
                error = step.error
                break
            try:
                run_primitive(env, step.skill, objects[step.target], np.asarray(step.target_centre_m),
                              objects.get(step.on) if step.on else None)
            except OutOfSteps:
                error = f"the step budget ({c.max_steps}) ran out"
            except PrimitiveFailure as e:
                step.error = error = str(e)
            except Exception as e:  # the planner raises on unreachable poses: a failed primitive, reported
                step.error = error = f"planner error: {type(e).__name__}: {e}"
            lap("execute")
            frame = self.sim.observe()[c.camera]
            objects = perception.perceive(frame)
            if trace is not None:
                trace.observed.append(frame)
                trace.targets.append(shown["target"](len(trace.observed)))
            lap("observe")
            if success_after is not None:
                state["now"] = bool(success_after())
                state["success"] |= state["now"]
            if error:
                break
        timings["simulate"] = watch_cls.sim_s
        timings["execute"] -= watch_cls.sim_s  # execute = motion planning; simulate = the env's steps
        result = EpisodeResult(self.sim.env_id, int(seed), source.name, state["success"], state["now"], watch_cls.steps,
                               replans, len([s for s in steps_taken if s.skill != "none"]),
                               time.perf_counter() - t_start, {k: round(v, 3) for k, v in timings.items()}, instruction,
                               error, [dict(s.__dict__) for s in steps_taken])
        return result


def _target_images(clip: FutureClip | None, frame, step: PlanStep, start: int):
    """index of the observed frame -> the image beside it in the MP4: the clip's frames in turn (the
    observation for the words arm), with the target drawn."""
    def image(i: int) -> np.ndarray:
        if clip is None:
            return draw_target(frame.rgb, step.target_centre_m, frame.K, frame.T_world_cam)
        t = min(max(i - start, 0), len(clip.rgb) - 1)
        return draw_target(clip.rgb[t], step.target_centre_m, clip.K[t], clip.T_world_cam[t])

    return image
