"""Motion-planned primitives toward a target pose, from perceived object poses only.

The skill library (``datagen.skills``) runs fixed skills from the simulator's object poses, for
datagen. The plan arms need the same motions toward any target, from what the camera showed
(:class:`tesseract4d.policy.perception.PerceivedObject`): push or pull an object to an xy, pick it up
and place it at an xyz, lift it to an xyz and hold it, stack it on another object. They run on
ManiSkill's ``PandaArmMotionPlanningSolver`` with the skill library's motions (screw moves; a closed
gripper as the pusher, 5 cm behind the object; a top-down grasp that closes across the object's side
faces) and its heights (``datagen.skills.LIFT_M``).

All positions are world metres. ``run_primitive`` raises :class:`PrimitiveFailure` when the planner
finds no path.
"""

from __future__ import annotations

import numpy as np

from datagen.skills import LIFT_M

PUSH_BEHIND_M = 0.05  # the gripper starts this far behind the object's centre
CONTACT_TRAVEL_M = 0.02  # ... and touches it after about this much travel
PLACE_ABOVE_M = 0.005  # an object is let go this far above where it should rest
SKILLS = ("push", "pull", "pick_place", "lift", "stack")


class PrimitiveFailure(Exception):
    """No motion plan for a primitive's move."""


def grasp_closing(face_yaw_rad: float, tcp_closing: np.ndarray) -> np.ndarray:
    """(3,) the unit closing direction of a top-down grasp: the side-face normal (of the two axes at
    ``face_yaw_rad`` about +z) closest to the gripper's present closing axis ``tcp_closing`` (3,), signed
    like it, so the wrist turns as little as possible."""
    a = np.array([np.cos(face_yaw_rad), np.sin(face_yaw_rad), 0.0])
    b = np.array([-np.sin(face_yaw_rad), np.cos(face_yaw_rad), 0.0])
    best = a if abs(a @ tcp_closing) >= abs(b @ tcp_closing) else b
    return best if best @ tcp_closing >= 0 else -best


def push_path(centre: np.ndarray, target_xy: np.ndarray) -> list[np.ndarray]:
    """The gripper's waypoints (4 x (3,)) of a push (or pull: a push toward the robot) of an object at
    ``centre`` (3,) so that its centre ends at ``target_xy`` (2,): above the contact point, the contact
    point, the push end, back up."""
    d = np.zeros(3)
    d[:2] = np.asarray(target_xy, np.float64) - centre[:2]
    dist = float(np.linalg.norm(d))
    d /= max(dist, 1e-9)
    pre = np.asarray(centre, np.float64) - d * PUSH_BEHIND_M
    end = pre + d * (dist + CONTACT_TRAVEL_M)
    up = np.array([0.0, 0.0, LIFT_M])
    return [pre + up, pre, end, end + up]


def run_primitive(env, skill: str, obj, target_centre: np.ndarray | None = None, on=None) -> None:
    """Execute ``skill`` on the wrapped ManiSkill ``env`` for the perceived object ``obj``.

    push / pull: slide ``obj`` so its centre ends at ``target_centre[:2]``; pick_place: carry it so its
    centre ends at ``target_centre`` (on the table) and let go; lift: carry its centre to
    ``target_centre`` and hold it there; stack: set it on the perceived object ``on`` and let go.
    """
    import sapien
    from mani_skill.examples.motionplanning.panda.motionplanner import PandaArmMotionPlanningSolver

    if skill not in SKILLS:
        raise ValueError(f"unknown primitive {skill!r}; primitives: {', '.join(SKILLS)}")
    base = env.unwrapped
    planner = PandaArmMotionPlanningSolver(env, debug=False, vis=False, base_pose=base.agent.robot.pose,
                                           visualize_target_grasp_pose=False, print_env_info=False)
    q_down = base.agent.tcp.pose.sp.q  # the gripper's start orientation: pointing down
    centre = np.asarray(obj.centre_world_m, np.float64)

    def move(p, q=None, what="move"):
        res = planner.move_to_pose_with_screw(sapien.Pose(p=np.asarray(p, np.float64), q=q_down if q is None else q))
        if isinstance(res, int) and res == -1:
            raise PrimitiveFailure(f"no motion plan to {what}")

    try:
        if skill in ("push", "pull"):
            planner.close_gripper()
            for p, what in zip(push_path(centre, np.asarray(target_centre)[:2]),
                               ("above the contact point", "the contact point", "the push end", "retreat")):
                move(p, what=what)
            return
        tcp_closing = base.agent.tcp.pose.to_transformation_matrix()[0, :3, 1].cpu().numpy().astype(np.float64)
        closing = grasp_closing(obj.face_yaw_rad, tcp_closing)
        grasp = base.agent.build_grasp_pose(np.array([0.0, 0.0, -1.0]), closing, centre)
        lift = np.array([0.0, 0.0, LIFT_M])
        move(grasp.p + [0, 0, 0.05], grasp.q, what="above the grasp")
        move(grasp.p, grasp.q, what="the grasp")
        planner.close_gripper()
        if skill == "lift":
            move(grasp.p + (np.asarray(target_centre) - centre), grasp.q, what="the lift goal")
            planner.close_gripper(t=6)
            return
        move(grasp.p + lift, grasp.q, what="the carry height")
        if skill == "stack":
            target_centre = np.asarray(on.centre_world_m, np.float64) + [0, 0, on.half_height_m + obj.half_height_m]
        goal = grasp.p + (np.asarray(target_centre, np.float64) - centre)
        move(goal + lift, grasp.q, what="above the place")
        move(goal + [0, 0, PLACE_ABOVE_M], grasp.q, what="the place")
        planner.open_gripper()
        move(goal + lift, grasp.q, what="retreat")
    finally:
        planner.close()
