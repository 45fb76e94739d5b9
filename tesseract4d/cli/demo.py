"""The one-command demo: render a held-out scene, predict two futures of it from two instructions
with the shipped checkpoint (a counterfactual pair: the same first frame, different words),
reconstruct both as 4D point clouds, write MP4/PLY/HTML and serve the viewer with the two futures
side by side.

The default scene is the project's multi-object tabletop (``Tesseract4dTabletop-v1``) at the first
held-out seed. Its instructions are the held-out paraphrases a counterfactual group gives two
skills (``datagen.counterfactual.commanded_future``): ``--skill`` (default ``push_left``: push
the first object of the scene, cubes before the cylinder, that has room to go left) and ``--contrast-skill`` (default ``keep_still``). A plain
ManiSkill task (``--task PickCube-v1``) keeps its own held-out task instruction; its contrast is
``keep_still`` where the skill library knows the scene (PickCube, PushCube, PullCube,
StackCube) and none elsewhere unless ``--contrast-instruction`` gives one.

Outputs under --out: first_frame/ (the rendered scene, dataset format), prediction/ (the main
future, dataset format, with MP4 previews), reconstruction/ (Recon4D: NPZ, PLY per frame,
background mesh), scene.html (standalone recording, opens from disk), instruction.txt; the
contrast future under contrast/ with the same names but first_frame/ (both start from it); side_by_side.mp4 (both futures, each under
its instruction); demo_config.json (the resolved config, both instructions included).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

from datagen.tabletop import ENV_ID as TABLETOP_ID
from tesseract4d.cli.argument_types import seed, whole
from tesseract4d.cli.config_args import PRECISION_MOVED, add_moved_to_set, add_set_option, dataclass_from_args
from tesseract4d.configs import knob
from tesseract4d.dataset_format import HELDOUT_SEED_START
from tesseract4d.errors import UserError
from tesseract4d.precision import precision_field
from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT

# The skills whose futures the demo contrasts by default (datagen.skills.VARIANTS).
DEFAULT_SKILL = "push_left"  # in scenes without a task of their own (the tabletop)
DEFAULT_CONTRAST_SKILL = "keep_still"
CONTRAST_DIR = "contrast"
SIDE_BY_SIDE = "side_by_side.mp4"


@dataclass
class DemoConfig:
    task: str = TABLETOP_ID
    seed: int = HELDOUT_SEED_START
    instruction: str | None = None  # None: from `skill`, or the task's own held-out instruction
    skill: str | None = None  # None: DEFAULT_SKILL in the tabletop, the task's instruction elsewhere
    contrast_instruction: str | None = None  # None: from `contrast_skill`
    contrast_skill: str | None = DEFAULT_CONTRAST_SKILL
    contrast: bool = knob(True, "predict the contrast future too (false: the main instruction's only)")
    checkpoint: Path = SHIPPED_CHECKPOINT
    out: Path = Path("demo_out")
    num_frames: int | None = knob(None, "frames to predict (none: one clip, the checkpoint preset's length)")
    steps: int | None = None  # None: the checkpoint preset's
    draws: int | None = knob(None, "noise draws per future, the one whose objects keep their colours best kept "
                                   "(none: the checkpoint preset's; 1 = a single draw)")
    sample_seed: int = knob(0, "noise seed of the predictions")
    camera: str | None = knob(None, "camera preset to render the first frame from (none: the checkpoint's)")
    host: str = knob("127.0.0.1", "viewer host (0.0.0.0 serves every address)")
    port: int = knob(8080, "viewer port")
    headless: bool = False
    precision: str = precision_field()
    overwrite: bool = False


def add_arguments(parser: argparse.ArgumentParser) -> None:
    d = DemoConfig()
    parser.add_argument("--task", default=d.task,
                        help="scene: the project's tabletop or a ManiSkill task id such as PickCube-v1 (default %(default)s)")
    parser.add_argument("--seed", type=seed(), default=d.seed,
                        help=f"scene seed; seeds >= {HELDOUT_SEED_START} are never used in training (default %(default)s)")
    parser.add_argument("--instruction", default=None,
                        help="the main instruction (default: the held-out paraphrase of --skill in the tabletop, "
                             "the task's own held-out instruction in a ManiSkill task)")
    parser.add_argument("--skill", metavar="VARIANT[@OBJECT]",
                        help=f"skill whose instruction is the main one when --instruction is not given (default "
                             f"{DEFAULT_SKILL} in the tabletop, none in a ManiSkill task); see datagen --skills")
    parser.add_argument("--contrast-instruction", metavar="TEXT",
                        help="the second instruction, predicted from the same first frame and noise (default: the "
                             "held-out paraphrase of --contrast-skill where the skill library knows the scene: the "
                             "tabletop, PickCube, PushCube, PullCube, StackCube; no contrast in other tasks)")
    parser.add_argument("--contrast-skill", default=d.contrast_skill, metavar="VARIANT[@OBJECT]",
                        help="skill whose instruction is the contrast when --contrast-instruction is not given "
                             "(default %(default)s)")
    parser.add_argument("--checkpoint", type=Path, default=d.checkpoint, help="model checkpoint folder (default: the shipped v2-2step, tesseract4d/checkpoints/v2-2step; tesseract4d/checkpoints/v2 is its 10-step teacher)")
    parser.add_argument("--out", type=Path, default=d.out, help="output folder (default %(default)s)")
    parser.add_argument("--steps", type=whole(1), help="sampler steps (default: the checkpoint preset's)")
    parser.add_argument("--headless", action="store_true", help="write the outputs and exit without serving the viewer")
    parser.add_argument("--overwrite", action="store_true",
                        help="write into a folder holding other files (only the demo's own files are replaced)")
    add_set_option(parser, DemoConfig)
    add_moved_to_set(parser, DemoConfig, [
        ("--num-frames", "num_frames", whole(1)), ("--draws", "draws", whole(1, hint=" (1: a single draw)")),
        ("--camera", "camera"), ("--host", "host"), ("--port", "port", whole(0, 65535)), PRECISION_MOVED,
        ("--sample-seed", "sample_seed", seed()), ("--no-contrast", "contrast", None, False),
    ])


def run(args: argparse.Namespace) -> int:
    cfg = dataclass_from_args(DemoConfig, args)
    outputs = run_demo(cfg)
    instruction = outputs["instruction"].read_text().strip()
    print(f"instruction: {instruction}")
    contrast = outputs.get("contrast instruction")
    if contrast is not None:
        print(f"contrast:    {contrast.read_text().strip()}")
    for name, path in outputs.items():
        print(f"  {name:<24} {path}")
    if cfg.headless:
        return 0
    from viewer.app import ViewerApp, serve_forever

    pair = {} if contrast is None else {"compare": outputs["contrast reconstruction"],
                                        "labels": (instruction, contrast.read_text().strip())}
    serve_forever(ViewerApp.from_path(outputs["reconstruction"], host=cfg.host, port=cfg.port, checkpoint=cfg.checkpoint,
                                      precision=cfg.precision, **pair))
    return 0


def run_demo(cfg: DemoConfig) -> dict[str, Path]:
    """Render → predict (one or two futures) → reconstruct → export into a staging folder moved to
    cfg.out at the end. Returns the paths written."""
    from tesseract4d.outputs import OutputDir

    _check_config(cfg)
    if not Path(cfg.checkpoint).is_dir():
        raise UserError(f"checkpoint {cfg.checkpoint} not found; pass --checkpoint DIR (a folder written by `tesseract4d checkpoint export`).")
    final = Path(cfg.out)
    with OutputDir(final, "demo", inputs=[cfg.checkpoint], overwrite=cfg.overwrite) as stage:
        written = _run_demo_stages(cfg, stage)
    return {name: final / path.relative_to(stage) for name, path in written.items()}


def _check_config(cfg: DemoConfig) -> None:
    """Refuse contradicting options before anything is loaded or rendered."""
    from datagen import skills as sk
    from tesseract4d.model.text_encoder import check_instruction

    if not cfg.contrast and cfg.contrast_instruction is not None:
        raise UserError("--set contrast=false and --contrast-instruction contradict each other; drop one")
    if cfg.instruction is not None and cfg.skill is not None:
        raise UserError("--instruction and --skill both set the main instruction; drop one")
    for flag, text in (("--instruction", cfg.instruction), ("--contrast-instruction", cfg.contrast_instruction)):
        check_instruction(text, flag)
        if text is not None and not text.strip():
            raise UserError(f"{flag} is empty; say what should happen, e.g. {flag} \"push the red cube to the left\"")
    if cfg.skill is not None:
        sk.parse_skill_list(cfg.skill, [cfg.task])
    if cfg.contrast and cfg.contrast_instruction is None and cfg.task in sk.SCENES:
        sk.parse_skill_list(cfg.contrast_skill, [cfg.task])


def resolve_instructions(cfg: DemoConfig, sim, first) -> tuple[str, str | None, dict]:
    """(main instruction, contrast instruction or None, the skills they came from) for the scene
    of ``cfg.seed`` rendered as ``first`` by ``sim`` (see the module docstring for the defaults)."""
    from datagen import skills as sk
    from datagen.counterfactual import commanded_future
    from datagen.tasks import get_task

    skills: dict[str, str | None] = {"skill": None, "contrast_skill": None}
    if cfg.instruction is not None:
        main = cfg.instruction.strip()
    elif cfg.skill is not None or get_task(cfg.task).skills_only:
        skills["skill"] = cfg.skill or DEFAULT_SKILL
        main = commanded_future(sim, cfg.seed, skills["skill"])[0]
    else:
        main = first.instruction
    contrast = None
    if cfg.contrast_instruction is not None:
        contrast = cfg.contrast_instruction.strip()
    elif cfg.contrast and cfg.task in sk.SCENES:
        skills["contrast_skill"] = cfg.contrast_skill
        contrast = commanded_future(sim, cfg.seed, cfg.contrast_skill)[0]
    if contrast is not None and contrast == main:
        raise UserError(f"the contrast instruction is the main one ({main!r}); pass another --contrast-instruction "
                        f"or --contrast-skill, or --set contrast=false")
    return main, contrast, skills


def _run_demo_stages(cfg: DemoConfig, out: Path) -> dict[str, Path]:
    from tqdm import tqdm

    from datagen.simulate import first_frame_simulator
    from reconstruction.reconstruct import ReconConfig, reconstruct_episode
    from tesseract4d import dataset_format as df
    from tesseract4d.model.predict import instruction_budget_note, load_pipeline, predict_counterfactuals, write_prediction
    from tesseract4d.previews import write_side_by_side
    from viewer.export import export_html

    stages = tqdm(total=4, desc="demo", unit="stage")

    stages.set_postfix_str(f"render {cfg.task} seed {cfg.seed}")
    pipeline = load_pipeline(cfg.checkpoint, precision=cfg.precision)
    height, width = pipeline.resolution
    camera = cfg.camera or pipeline.camera_name or "close"
    sim = first_frame_simulator(cfg.task, height=height, width=width, camera=camera)
    try:
        first = sim.first_frame(cfg.seed)
        main, contrast, skills = resolve_instructions(cfg, sim, first)
    finally:
        sim.close()
    if contrast is None and cfg.contrast:
        stages.write(f"note: one future only: the skill library does not know {cfg.task}'s scene; pass "
                     f"--contrast-instruction TEXT for a second one")
    instructions = [main] + ([contrast] if contrast is not None else [])
    # The resolved config: instructions, camera, frames and steps as used.
    cfg = dataclasses.replace(cfg, instruction=main, contrast_instruction=contrast, contrast=contrast is not None,
                              camera=camera, num_frames=cfg.num_frames or pipeline.num_frames,
                              steps=cfg.steps or pipeline.preset.num_steps,
                              draws=pipeline.preset.draws if cfg.draws is None else cfg.draws, **skills)
    (out / "demo_config.json").write_text(json.dumps(dataclasses.asdict(cfg), indent=2, default=str))
    for text in instructions:
        if note := instruction_budget_note(pipeline, text):
            stages.write(note)
    first_path = df.write_episode_dataset(out / "first_frame", first)
    stages.update()

    stages.set_postfix_str("predict: " + " | ".join(repr(t) for t in instructions))
    preds = predict_counterfactuals(pipeline, first, instructions, num_frames=cfg.num_frames, seed=cfg.sample_seed,
                                    num_steps=cfg.steps, draws=cfg.draws)
    # (folder, predicted episode, instruction, output-name prefix) per future
    futures = [(out, preds[0], main, "")] + ([(out / CONTRAST_DIR, preds[1], contrast, "contrast ")] if contrast is not None else [])
    written = {"first frame": first_path}
    for folder, pred, text, prefix in futures:
        written[prefix + "prediction"] = write_prediction(pred, folder / "prediction")
    stages.update()

    stages.set_postfix_str("reconstruct")
    recons = []
    for folder, pred, text, prefix in futures:
        recon = reconstruct_episode(pred, config=ReconConfig())
        recon.metadata.update({"instruction": text, "task": cfg.task, "seed": cfg.seed})
        written[prefix + "reconstruction"] = recon.save(folder / "reconstruction", staged=True)
        recons.append(recon)
    stages.update()

    stages.set_postfix_str("export html and mp4")
    for (folder, pred, text, prefix), recon in zip(futures, recons):
        written[prefix + "html"] = export_html(recon, folder / "scene.html")
        (folder / "instruction.txt").write_text(text + "\n")
        written[prefix + "instruction"] = folder / "instruction.txt"
    if contrast is not None:
        written["side by side"] = write_side_by_side(out / SIDE_BY_SIDE, preds, instructions)
    stages.update()
    stages.close()
    return written
