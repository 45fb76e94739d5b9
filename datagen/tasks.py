"""The task registry: which ManiSkill tasks datagen supports and what it records of each.

A task is supported when ManiSkill ships a motion-planner solution for it
(``mani_skill.examples.motionplanning.panda.run.MP_SOLUTIONS``) and its assets come inside the
wheel, so it runs offline; the project's own multi-object scene (``datagen/tabletop.py``) is
supported through the skill library (``datagen/skills.py``). Each entry names the scene actors whose world poses are recorded
(``object_poses/<name>``), the actors whose colour ``--randomize-colors`` changes, and where the
``close`` camera preset looks (see cameras.py).

World frame of these tabletop tasks: the robot base stands at x = -0.615 facing +x, the table
top is z = 0, objects start within about ±0.1 m of the origin. Units: metres.
"""

from __future__ import annotations

from dataclasses import dataclass

from datagen.tabletop import ENV_ID as TABLETOP_ID
from datagen.tabletop import OBJECTS as TABLETOP_OBJECTS
from tesseract4d.errors import UserError

CONTROL_MODE = "pd_joint_pos"


@dataclass(frozen=True)
class TaskSpec:
    """What datagen needs to know about one ManiSkill task."""

    env_id: str
    # (recorded name, env attribute) of the actors whose (T, 7) world poses are recorded
    objects: tuple[tuple[str, str], ...]
    colorable: tuple[str, ...] = ()  # recorded names recoloured by --randomize-colors, in instruction order
    default_colors: tuple[str, ...] = ()  # colour names of `colorable` as ManiSkill builds them
    # The "close" camera: eye and look-at target in world metres, vertical field of view in degrees.
    close_eye: tuple[float, float, float] = (0.24, -0.30, 0.40)
    close_target: tuple[float, float, float] = (-0.03, 0.0, 0.05)
    close_fov_deg: float = 50.0
    # True for the project's own scenes, which have no single task: datagen runs skills in them
    # (datagen/skills.py), never a ManiSkill motion-planning solution.
    skills_only: bool = False


TASKS: dict[str, TaskSpec] = {
    spec.env_id: spec
    for spec in [
        TaskSpec("PickCube-v1", objects=(("cube", "cube"), ("goal", "goal_site")), colorable=("cube",), default_colors=("red",),
                 close_target=(-0.03, 0.0, 0.11), close_fov_deg=56.0),
        TaskSpec("PushCube-v1", objects=(("cube", "obj"), ("goal", "goal_region")), colorable=("cube",), default_colors=("blue",)),
        TaskSpec("PullCube-v1", objects=(("cube", "obj"), ("goal", "goal_region")), colorable=("cube",), default_colors=("blue",)),
        TaskSpec("StackCube-v1", objects=(("cubeA", "cubeA"), ("cubeB", "cubeB")), colorable=("cubeA", "cubeB"),
                 default_colors=("red", "green")),
        TaskSpec("LiftPegUpright-v1", objects=(("peg", "peg"),), close_target=(-0.03, 0.0, 0.08), close_fov_deg=54.0),
        TaskSpec("PullCubeTool-v1", objects=(("cube", "cube"), ("tool", "l_shape_tool")), colorable=("cube",), default_colors=("blue",),
                 close_eye=(0.25, -0.45, 0.42), close_target=(-0.12, -0.02, 0.02), close_fov_deg=60.0),
        TaskSpec("PlugCharger-v1", objects=(("charger", "charger"), ("receptacle", "receptacle")), close_target=(-0.03, 0.0, 0.07)),
        TaskSpec("PegInsertionSide-v1", objects=(("peg", "peg"), ("box", "box")),
                 close_eye=(0.25, -0.42, 0.40), close_target=(-0.02, 0.05, 0.06), close_fov_deg=60.0),
        TaskSpec(TABLETOP_ID, objects=tuple((n, n) for n in TABLETOP_OBJECTS) + (("goal", "goal_site"),),
                 close_eye=(0.30, -0.40, 0.42), close_target=(-0.02, 0.0, 0.04), close_fov_deg=52.0, skills_only=True),
    ]
}

# ManiSkill tasks that only run after downloading assets (`python -m mani_skill.utils.download_asset ...`).
# Prefixes of their ids, for a clear error instead of a hang or a crash deep in the simulator.
ASSET_TASK_PREFIXES: dict[str, str] = {
    "PickSingleYCB": "ycb",
    "PickClutterYCB": "ycb",
    "PickSingleEGAD": "egad",
    "OpenCabinet": "partnet_mobility_cabinet",
    "TurnFaucet": "partnet_mobility_faucet",
    "ReplicaCAD": "ReplicaCAD",
    "SceneManipulation": "ReplicaCAD",
    "RoboCasa": "RoboCasa",
    "PutCarrotOnPlate": "bridge_v2_real2sim",
    "PutEggplantInBasket": "bridge_v2_real2sim",
    "PutSpoonOnTableCloth": "bridge_v2_real2sim",
    "StackGreenCubeOnYellowCube": "bridge_v2_real2sim",
}


def valid_task_ids() -> list[str]:
    return list(TASKS)


def get_task(env_id: str) -> TaskSpec:
    """The spec of a supported task, or a UserError that says which ids are valid (and why not)."""
    if env_id in TASKS:
        return TASKS[env_id]
    for prefix, asset in ASSET_TASK_PREFIXES.items():
        if env_id.startswith(prefix):
            raise UserError(
                f"task {env_id!r} needs downloaded assets ({asset}: `python -m mani_skill.utils.download_asset {asset}`) "
                f"and has no motion-planner solution, so datagen cannot generate it offline. "
                f"Supported tasks: {', '.join(TASKS)}"
            )
    raise UserError(f"unknown or unsupported task {env_id!r}; supported tasks: {', '.join(TASKS)}")


def parse_task_list(text: str) -> list[str]:
    """'PickCube-v1,PushCube-v1' (or 'all') -> validated list of ids, order kept, duplicates dropped."""
    if text.strip() == "all":
        return valid_task_ids()
    ids = [t.strip() for t in text.split(",") if t.strip()]
    if not ids:
        raise UserError(f"--tasks is empty; give a comma-separated list of: {', '.join(TASKS)} (or 'all')")
    for t in ids:
        get_task(t)
    return list(dict.fromkeys(ids))
