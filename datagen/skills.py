"""The skill library: parametrised manipulation skills on ManiSkill's Panda motion planner.

A *skill variant* (``VARIANTS``) is a skill with fixed parameters, e.g. ``push_left`` = push
the target object 10 cm to the left. Executed on a reset env with a target object (and another
object for ``stack``), it drives ManiSkill's ``PandaArmMotionPlanningSolver`` (screw motions,
gripper open/close: the solver of ManiSkill's own motion-planning solutions) and then judges
success from object poses only (``check_intent``), so the same check can score predictions.

Directions are in the robot's frame as ``datagen.instructions`` defines them: the robot stands
at x < 0 facing +x, so forward = +x, back = -x, left = +y, right = -y (``DIRECTIONS``; their
words come from ``instructions.direction_words``). Units: metres, world frame.

Scenes: the project's multi-object tabletop (``datagen.tabletop``) and, where a skill applies,
the single-task scenes PickCube, PushCube, PullCube (one cube) and StackCube (two cubes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from datagen.tabletop import ENV_ID as TABLETOP_ID
from datagen.tabletop import OBJECTS as TABLETOP_OBJECTS
from tesseract4d.errors import UserError

DIRECTIONS: dict[str, tuple[float, float, float]] = {
    "forward": (1.0, 0.0, 0.0),
    "back": (-1.0, 0.0, 0.0),
    "left": (0.0, 1.0, 0.0),
    "right": (0.0, -1.0, 0.0),
}
# Named gripper places for ``reach_*`` (world xyz, metres): beside the workspace, above the table.
PLACES: dict[str, tuple[float, float, float]] = {"left": (0.0, 0.25, 0.18), "right": (0.0, -0.25, 0.18)}

# Success thresholds (metres): also the scoring contract stored with every episode.
OTHERS_STILL_M = 0.005  # objects a skill does not target move less than this
STILL_OBJECT_M = 0.001  # keep_still: no object moves more than this
STILL_GRIPPER_M = 0.01  # keep_still: the gripper moves less than this
MIN_COS = 0.9  # displacement direction vs commanded direction
GRIPPER_GOAL_M = 0.02  # hover/reach: the gripper ends this close to its goal
HOVER_HEIGHT_M = 0.12  # hover_above: gripper this far above the object's centre
KEEP_STILL_STEPS = 40  # 2 s at ManiSkill's 20 Hz control

LIFT_M = 0.08  # carrying height above the grasp
_CLEARANCE_M = 0.065  # free space kept around a push path or a placement spot
_TABLE_XY = ((-0.2, 0.25), (-0.3, 0.3))  # where targets may lie (reachable table area)


@dataclass(frozen=True)
class SkillVariant:
    """One skill with fixed parameters."""

    name: str
    skill: str  # push | pull | pick_place | lift | stack | hover | reach | keep_still
    direction: str | None = None  # a key of DIRECTIONS (push/pull/pick_place) or PLACES (reach)
    distance_m: float = 0.0  # push/pull/pick_place travel, lift height
    needs_target: bool = True
    needs_other: bool = False


VARIANTS: dict[str, SkillVariant] = {
    v.name: v
    for v in [
        SkillVariant("push_forward", "push", "forward", 0.10),
        SkillVariant("push_left", "push", "left", 0.10),
        SkillVariant("push_right", "push", "right", 0.10),
        SkillVariant("pull_back", "pull", "back", 0.10),
        SkillVariant("lift", "lift", None, 0.12),
        SkillVariant("place_left", "pick_place", "left", 0.12),
        SkillVariant("place_right", "pick_place", "right", 0.12),
        SkillVariant("place_forward", "pick_place", "forward", 0.10),
        SkillVariant("stack", "stack", needs_other=True),
        SkillVariant("hover_above", "hover"),
        SkillVariant("reach_left", "reach", "left", needs_target=False),
        SkillVariant("reach_right", "reach", "right", needs_target=False),
        SkillVariant("keep_still", "keep_still", needs_target=False),
    ]
}


@dataclass(frozen=True)
class SceneObject:
    """A movable object of a scene: recorded name, env attribute, shape word, half height (m)."""

    name: str
    attr: str
    shape: str
    half_height_m: float
    default_color: str = ""


# Scenes the skills run in. The tabletop's objects present and their colours change per episode.
SCENES: dict[str, tuple[SceneObject, ...]] = {
    TABLETOP_ID: tuple(SceneObject(n, n, shape, h) for n, (shape, h) in TABLETOP_OBJECTS.items()),
    "PickCube-v1": (SceneObject("cube", "cube", "cube", 0.02, "red"),),
    "PushCube-v1": (SceneObject("cube", "obj", "cube", 0.02, "blue"),),
    "PullCube-v1": (SceneObject("cube", "obj", "cube", 0.02, "blue"),),
    "StackCube-v1": (SceneObject("cubeA", "cubeA", "cube", 0.02, "red"), SceneObject("cubeB", "cubeB", "cube", 0.02, "green")),
}


class SkillFailure(Exception):
    """A skill could not be executed (no motion plan); the episode is a reported failure."""


# --------------------------------------------------------------------------- validation


def skill_scenes() -> list[str]:
    return list(SCENES)


def applies(variant: SkillVariant, env_id: str) -> bool:
    """Whether ``variant`` can run in ``env_id``'s scene at all (enough objects)."""
    if env_id not in SCENES:
        return False
    return len(SCENES[env_id]) >= 1 + int(variant.needs_other)


def parse_skill_list(text: str | None, env_ids: list[str]) -> list[str] | None:
    """'push_left,stack@cube_a' (or 'all' / None) -> validated list of skill specs.

    A spec is ``VARIANT`` or ``VARIANT@OBJECT`` (pin the target object). Every spec must apply
    to every task in ``env_ids``. None or 'all' means every variant that applies (returns None).
    """
    for env_id in env_ids:
        if env_id not in SCENES:
            raise UserError(f"skills do not run in {env_id}'s scene; scenes with skills: {', '.join(SCENES)}")
    if text is None or text.strip() == "all":
        return None
    specs = [s.strip() for s in text.split(",") if s.strip()]
    if not specs:
        raise UserError(f"--skills is empty; choose from {', '.join(VARIANTS)} (or 'all')")
    for spec in specs:
        name, _, obj = spec.partition("@")
        if name not in VARIANTS:
            raise UserError(f"unknown skill {name!r}; choose from {', '.join(VARIANTS)}")
        for env_id in env_ids:
            if not applies(VARIANTS[name], env_id):
                valid = [v for v in VARIANTS if applies(VARIANTS[v], env_id)]
                raise UserError(f"skill {name!r} does not apply to {env_id}'s scene (it needs two objects); "
                                f"skills for {env_id}: {', '.join(valid)}")
            names = [o.name for o in SCENES[env_id]]
            if obj and obj not in names:
                raise UserError(f"object {obj!r} is not in {env_id}'s scene; objects: {', '.join(names)}")
            if obj and not VARIANTS[name].needs_target:
                raise UserError(f"skill {name!r} has no target object; drop '@{obj}'")
    return list(dict.fromkeys(specs))


def available_variants(env_id: str, specs: list[str] | None) -> list[str]:
    """The distinct variant names a group in ``env_id`` may draw from."""
    if specs is None:
        return [v for v in VARIANTS if applies(VARIANTS[v], env_id)]
    return list(dict.fromkeys(s.partition("@")[0] for s in specs))


def check_group_size(k: int, env_ids: list[str], specs: list[str] | None) -> None:
    """K futures per scene need K distinct skill variants; say which exist when there are fewer."""
    if k < 1:
        raise UserError(f"--instructions-per-scene must be at least 1, got {k}")
    for env_id in env_ids:
        names = available_variants(env_id, specs)
        if k > len(names):
            raise UserError(f"--instructions-per-scene {k} needs {k} distinct skills but {env_id} has "
                            f"{len(names)}: {', '.join(names)}")


# --------------------------------------------------------------------------- the scene


def present_objects(env_id: str, base_env) -> list[SceneObject]:
    """The scene's movable objects on the table now (after reset)."""
    objs = SCENES[env_id]
    if env_id == TABLETOP_ID:
        return [o for o in objs if o.name in base_env.present]
    return list(objs)


def object_colors(env_id: str, base_env, appearance_colors: dict[str, str] | None = None) -> dict[str, str]:
    """Colour name of each present object (the tabletop draws them per episode; the single-task
    scenes have ManiSkill's colours unless ``datagen --set randomize_colors=true`` replaced them)."""
    if env_id == TABLETOP_ID:
        return dict(base_env.object_colors)
    appearance_colors = appearance_colors or {}
    return {o.name: appearance_colors.get(o.name, o.default_color) for o in SCENES[env_id]}


def object_positions(env_id: str, base_env) -> dict[str, np.ndarray]:
    """World xyz (3,) of every object of the scene's pool (parked ones included)."""
    return {o.name: getattr(base_env, o.attr).pose.p[0].cpu().numpy().astype(np.float64) for o in SCENES[env_id]}


def tcp_position(base_env) -> np.ndarray:
    return base_env.agent.tcp.pose.p[0].cpu().numpy().astype(np.float64)


# --------------------------------------------------------------------------- choosing a group


def candidates(env_id: str, base_env, variant: SkillVariant, pinned: str | None = None) -> list[tuple[str | None, str | None]]:
    """(target, other) pairs for which ``variant`` is geometrically feasible in this scene.

    Feasible = the push path / placement spot is on the reachable table and keeps
    ``_CLEARANCE_M`` from every other object, so a successful plan does not disturb them.
    """
    objs = present_objects(env_id, base_env)
    pos = {o.name: p for o, p in ((o, object_positions(env_id, base_env)[o.name]) for o in objs)}
    if not variant.needs_target:
        return [(None, None)]
    out = []
    for t in objs:
        if pinned and t.name != pinned:
            continue
        others = [pos[o.name][:2] for o in objs if o.name != t.name]
        start = pos[t.name][:2]
        if variant.skill in ("push", "pull", "pick_place"):
            d = np.asarray(DIRECTIONS[variant.direction][:2])
            end = start + d * variant.distance_m
            if not _on_table(end):
                continue
            # the gripper starts 5 cm behind the object (push/pull) or comes from above (pick_place)
            path_start = start - d * 0.05 if variant.skill != "pick_place" else end
            if any(_dist_to_segment(o, path_start, end) < _CLEARANCE_M for o in others):
                continue
            out.append((t.name, None))
        elif variant.needs_other:
            out.extend((t.name, o.name) for o in objs if o.name != t.name)
        else:
            out.append((t.name, None))
    return out


def _on_table(xy: np.ndarray) -> bool:
    (x0, x1), (y0, y1) = _TABLE_XY
    return x0 <= xy[0] <= x1 and y0 <= xy[1] <= y1


def _dist_to_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ab = b - a
    t = float(np.clip(np.dot(p - a, ab) / max(float(np.dot(ab, ab)), 1e-12), 0.0, 1.0))
    return float(np.linalg.norm(p - (a + t * ab)))


# --------------------------------------------------------------------------- intent


def commanded_intent(env_id: str, base_env, variant: SkillVariant, target: str | None, other: str | None) -> dict:
    """What the skill is asked to do, from the reset scene: the structured intent (no outcome yet).

    commanded_displacement_world_m: where the target object should move (world metres; zeros
    when no object should move). gripper_goal_world_m: where the gripper should end (hover/reach).
    """
    pos = object_positions(env_id, base_env)
    half = {o.name: o.half_height_m for o in SCENES[env_id]}
    cmd = np.zeros(3)
    gripper_goal = None
    if variant.skill in ("push", "pull", "pick_place"):
        cmd = np.asarray(DIRECTIONS[variant.direction]) * variant.distance_m
    elif variant.skill == "lift":
        cmd = np.array([0.0, 0.0, variant.distance_m])
    elif variant.skill == "stack":
        goal = pos[other] + np.array([0.0, 0.0, half[other] + half[target]])
        cmd = goal - pos[target]
    elif variant.skill == "hover":
        gripper_goal = pos[target] + np.array([0.0, 0.0, HOVER_HEIGHT_M])
    elif variant.skill == "reach":
        gripper_goal = np.asarray(PLACES[variant.direction])
    criteria = {
        "push": f"target moves along the commanded direction (cos > {MIN_COS}) by at least half the distance; "
                f"other objects move < {OTHERS_STILL_M * 1000:.0f} mm",
        "pick_place": f"target ends on the table moved along the commanded direction (cos > {MIN_COS}) within "
                      f"3 cm of the commanded distance and released; other objects move < {OTHERS_STILL_M * 1000:.0f} mm",
        "lift": "target is held at least (height - 3 cm) above its start; other objects move "
                f"< {OTHERS_STILL_M * 1000:.0f} mm",
        "stack": "target rests on the other object (centres within 2.5 cm in xy, height gap within 1 cm), released; "
                 f"remaining objects move < {OTHERS_STILL_M * 1000:.0f} mm",
        "hover": f"gripper ends within {GRIPPER_GOAL_M * 100:.0f} cm of its goal; no object moves "
                 f"> {OTHERS_STILL_M * 1000:.0f} mm",
        "keep_still": f"no object moves > {STILL_OBJECT_M * 1000:.0f} mm and the gripper < {STILL_GRIPPER_M * 100:.0f} cm",
    }
    kind = {"pull": "push", "reach": "hover"}.get(variant.skill, variant.skill)
    return {
        "skill": variant.skill,
        "variant": variant.name,
        "target": target,
        "other": other,
        "direction": variant.direction,
        "distance_m": variant.distance_m,
        "commanded_displacement_world_m": [float(v) for v in cmd],
        "gripper_goal_world_m": None if gripper_goal is None else [float(v) for v in gripper_goal],
        "criterion": criteria[kind],
        "objects_present": [o.name for o in present_objects(env_id, base_env)],
    }


def check_intent(intent: dict, start: dict[str, np.ndarray], end: dict[str, np.ndarray],
                 tcp_start: np.ndarray, tcp_end: np.ndarray, target_grasped: bool = False) -> dict:
    """Judge an intent from object positions only: the outcome fields of the structured intent.

    start, end: object name -> world xyz (3,) at the first and last frame, for the objects
    present. tcp_start, tcp_end: gripper (TCP) world xyz. target_grasped: whether the gripper
    holds the target at the end (lift must, pick_place/stack must not). Returns achieved
    displacement, the largest displacement of the other objects, the gripper's displacement and
    ``success``.
    """
    target, skill = intent["target"], intent["skill"]
    disp = {n: np.asarray(end[n], np.float64) - np.asarray(start[n], np.float64) for n in start}
    others = [n for n in disp if n != target]
    others_max = max((float(np.linalg.norm(disp[n])) for n in others), default=0.0)
    achieved = disp[target] if target else np.zeros(3)
    cmd = np.asarray(intent["commanded_displacement_world_m"], np.float64)
    gripper_moved = float(np.linalg.norm(np.asarray(tcp_end) - np.asarray(tcp_start)))
    cos = _cos(achieved[:2], cmd[:2])
    if skill in ("push", "pull"):
        ok = cos > MIN_COS and np.linalg.norm(achieved[:2]) >= 0.5 * np.linalg.norm(cmd[:2]) and others_max < OTHERS_STILL_M
    elif skill == "pick_place":
        ok = (cos > MIN_COS and abs(np.linalg.norm(achieved[:2]) - np.linalg.norm(cmd[:2])) < 0.03
              and abs(achieved[2]) < 0.01 and not target_grasped and others_max < OTHERS_STILL_M)
    elif skill == "lift":
        ok = achieved[2] >= cmd[2] - 0.03 and target_grasped and others_max < OTHERS_STILL_M
    elif skill == "stack":
        gap = achieved - cmd
        ok = np.linalg.norm(gap[:2]) <= 0.025 and abs(gap[2]) <= 0.01 and not target_grasped and others_max < OTHERS_STILL_M
    elif skill in ("hover", "reach"):
        goal = np.asarray(intent["gripper_goal_world_m"])
        ok = np.linalg.norm(np.asarray(tcp_end) - goal) < GRIPPER_GOAL_M and others_max < OTHERS_STILL_M
    elif skill == "keep_still":
        ok = others_max < STILL_OBJECT_M and gripper_moved < STILL_GRIPPER_M
    else:
        raise ValueError(f"unknown skill {skill!r}")
    return {
        "achieved_displacement_world_m": [float(v) for v in achieved],
        "direction_cos": None if skill in ("hover", "reach", "keep_still", "lift") else round(cos, 4),
        "others_max_displacement_m": others_max,
        "gripper_displacement_m": gripper_moved,
        "target_grasped_at_end": bool(target_grasped),
        "success": bool(ok),
    }


def _cos(a: np.ndarray, b: np.ndarray) -> float:
    na, nb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
    return float(np.dot(a, b) / (na * nb)) if na > 1e-9 and nb > 1e-9 else 0.0


# --------------------------------------------------------------------------- execution


def execute(env, env_id: str, variant: SkillVariant, target: str | None, other: str | None) -> None:
    """Run ``variant`` on the (already reset) wrapped ``env`` with ManiSkill's Panda planner.

    Raises SkillFailure when the planner finds no path. Success is judged afterwards by
    ``check_intent`` from object poses.
    """
    import sapien
    from mani_skill.examples.motionplanning.panda.motionplanner import PandaArmMotionPlanningSolver

    base = env.unwrapped
    planner = PandaArmMotionPlanningSolver(env, debug=False, vis=False, base_pose=base.agent.robot.pose,
                                           visualize_target_grasp_pose=False, print_env_info=False)
    half = {o.name: o.half_height_m for o in SCENES[env_id]}
    actor = {o.name: getattr(base, o.attr) for o in SCENES[env_id]}
    q_down = base.agent.tcp.pose.sp.q  # the gripper's start orientation: pointing down

    def move(p, q=None, what="move"):
        res = planner.move_to_pose_with_screw(sapien.Pose(p=np.asarray(p, np.float64), q=q_down if q is None else q))
        if isinstance(res, int) and res == -1:
            raise SkillFailure(f"no motion plan to {what}")

    try:
        if variant.skill == "keep_still":
            planner.open_gripper(t=KEEP_STILL_STEPS)
            return
        if variant.skill in ("hover", "reach"):
            goal = (object_positions(env_id, base)[target] + [0, 0, HOVER_HEIGHT_M] if variant.skill == "hover"
                    else np.asarray(PLACES[variant.direction]))
            move(goal, what=f"{variant.name} goal")
            planner.open_gripper(t=6)
            return
        p = object_positions(env_id, base)[target]
        if variant.skill in ("push", "pull"):
            d = np.asarray(DIRECTIONS[variant.direction])
            planner.close_gripper()
            pre = p - d * 0.05
            pre[2] = half[target]
            move(pre + [0, 0, LIFT_M], what="above the contact point")
            move(pre, what="the contact point")
            # the fingers touch the object after ~2 cm: travel that much further
            move(pre + d * (variant.distance_m + 0.02), what="the push end")
            move(pre + d * (variant.distance_m + 0.02) + [0, 0, LIFT_M], what="retreat")
            return
        grasp = _grasp_pose(base, actor[target])
        move(grasp.p + [0, 0, 0.05], grasp.q, what="above the grasp")
        move(grasp.p, grasp.q, what="the grasp")
        planner.close_gripper()
        if variant.skill == "lift":
            move(grasp.p + [0, 0, variant.distance_m], grasp.q, what="the lift height")
            planner.close_gripper(t=6)
            return
        move(grasp.p + [0, 0, LIFT_M], grasp.q, what="the carry height")
        if variant.skill == "pick_place":
            goal = grasp.p + np.asarray(DIRECTIONS[variant.direction]) * variant.distance_m
        else:  # stack: grasp offset kept, object bottom onto the other's top
            po = object_positions(env_id, base)[other]
            goal = grasp.p + (po + [0, 0, half[other] + half[target]] - p)
        move(goal + [0, 0, LIFT_M], grasp.q, what="above the place")
        move(goal + [0, 0, 0.005], grasp.q, what="the place")
        planner.open_gripper()
        move(goal + [0, 0, LIFT_M], grasp.q, what="retreat")
    finally:
        planner.close()


def _grasp_pose(base, actor):
    """A top-down grasp of ``actor`` from its oriented bounding box (as ManiSkill's pick solution)."""
    from mani_skill.examples.motionplanning.base_motionplanner.utils import compute_grasp_info_by_obb, get_actor_obb

    approaching = np.array([0, 0, -1])
    target_closing = base.agent.tcp.pose.to_transformation_matrix()[0, :3, 1].cpu().numpy()
    info = compute_grasp_info_by_obb(get_actor_obb(actor), approaching=approaching, target_closing=target_closing,
                                     depth=0.025)
    return base.agent.build_grasp_pose(approaching, info["closing"], actor.pose.sp.p)


def is_grasping(env_id: str, base_env, target: str | None) -> bool:
    if target is None:
        return False
    attr = {o.name: o.attr for o in SCENES[env_id]}[target]
    return bool(base_env.agent.is_grasping(getattr(base_env, attr))[0])
