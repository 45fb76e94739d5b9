"""The one-command demo: render a held-out ManiSkill scene, predict its RGB-D-N future from an
instruction with the shipped checkpoint, reconstruct the 4D point cloud, write MP4/PLY/HTML and
serve the viewer.

Outputs under --out: first_frame/ (the rendered scene, dataset format), prediction/ (the
predicted clip, dataset format, with MP4 previews), reconstruction/ (Recon4D: NPZ, PLY per frame,
background mesh), scene.html (standalone recording, opens from disk), demo_config.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

from tesseract4d.dataset_format import HELDOUT_SEED_START
from tesseract4d.errors import UserError
from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT


@dataclass
class DemoConfig:
    task: str = "PickCube-v1"
    seed: int = HELDOUT_SEED_START
    instruction: str | None = None
    checkpoint: Path = SHIPPED_CHECKPOINT
    out: Path = Path("demo_out")
    num_frames: int | None = None  # None: one clip of the checkpoint's preset
    steps: int | None = None  # None: the checkpoint preset's
    sample_seed: int = 0
    camera: str = "close"
    host: str = "127.0.0.1"
    port: int = 8080
    headless: bool = False
    precision: str = "auto"
    overwrite: bool = False


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from tesseract4d.precision import add_precision_argument

    d = DemoConfig()
    parser.add_argument("--task", default=d.task, help="ManiSkill task id (default %(default)s)")
    parser.add_argument("--seed", type=int, default=d.seed,
                        help=f"scene seed; seeds >= {HELDOUT_SEED_START} are never used in training (default %(default)s)")
    parser.add_argument("--instruction", default=None,
                        help="instruction text (default: a held-out paraphrase generated for the scene)")
    parser.add_argument("--checkpoint", type=Path, default=d.checkpoint, help="model checkpoint folder (default: the shipped tiny model)")
    parser.add_argument("--out", type=Path, default=d.out, help="output folder (default %(default)s)")
    parser.add_argument("--num-frames", type=int, help="frames to predict (default: one clip, the checkpoint preset's length)")
    parser.add_argument("--steps", type=int, help="sampler steps (default: the checkpoint preset's)")
    parser.add_argument("--sample-seed", type=int, default=d.sample_seed, help="diffusion noise seed (default %(default)s)")
    parser.add_argument("--camera", default=d.camera, help="camera preset to render the first frame from (default %(default)s)")
    parser.add_argument("--host", default=d.host, help="viewer host (default %(default)s)")
    parser.add_argument("--port", type=int, default=d.port, help="viewer port (default %(default)s)")
    parser.add_argument("--headless", action="store_true", help="write the outputs and exit without serving the viewer")
    add_precision_argument(parser)
    parser.add_argument("--overwrite", action="store_true",
                        help="write into a folder holding other files (only the demo's own files are replaced)")


def run(args: argparse.Namespace) -> int:
    cfg = DemoConfig(
        task=args.task, seed=args.seed, instruction=args.instruction, checkpoint=args.checkpoint, out=args.out,
        num_frames=args.num_frames, steps=args.steps, sample_seed=args.sample_seed, camera=args.camera,
        host=args.host, port=args.port, headless=args.headless, precision=args.precision, overwrite=args.overwrite,
    )
    outputs = run_demo(cfg)
    print(f"instruction: {outputs['instruction'].read_text().strip()}")
    for name, path in outputs.items():
        print(f"  {name:<16} {path}")
    if cfg.headless:
        return 0
    from viewer.app import ViewerApp, serve_forever

    serve_forever(ViewerApp.from_path(outputs["reconstruction"], host=cfg.host, port=cfg.port, checkpoint=cfg.checkpoint))
    return 0


def run_demo(cfg: DemoConfig) -> dict[str, Path]:
    """Render → predict → reconstruct → export into a staging folder moved to cfg.out at the end.
    Returns the paths written."""
    from tesseract4d.outputs import OutputDir

    if not Path(cfg.checkpoint).is_dir():
        raise UserError(f"checkpoint {cfg.checkpoint} not found; pass --checkpoint DIR (a folder written by `tesseract4d train --export`).")
    final = Path(cfg.out)
    with OutputDir(final, "demo", inputs=[cfg.checkpoint], overwrite=cfg.overwrite) as stage:
        written = _run_demo_stages(cfg, stage)
    return {name: final / path.relative_to(stage) for name, path in written.items()}


def _run_demo_stages(cfg: DemoConfig, out: Path) -> dict[str, Path]:
    from tqdm import tqdm

    from datagen.simulate import render_first_frame
    from reconstruction.reconstruct import ReconConfig, reconstruct_episode
    from tesseract4d import dataset_format as df
    from tesseract4d.model.predict import instruction_budget_note, load_pipeline, predict_episode, write_prediction
    from viewer.export import export_html

    stages = tqdm(total=4, desc="demo", unit="stage")

    stages.set_postfix_str(f"render {cfg.task} seed {cfg.seed}")
    pipeline = load_pipeline(cfg.checkpoint, precision=cfg.precision)
    # The resolved config: frames and steps the checkpoint's preset gives when not set.
    cfg = dataclasses.replace(cfg, num_frames=cfg.num_frames or pipeline.num_frames, steps=cfg.steps or pipeline.preset.num_steps)
    (out / "demo_config.json").write_text(json.dumps(dataclasses.asdict(cfg), indent=2, default=str))
    height, width = pipeline.resolution
    first = render_first_frame(cfg.task, cfg.seed, height=height, width=width, camera=cfg.camera)
    instruction = cfg.instruction if cfg.instruction is not None else first.instruction
    if note := instruction_budget_note(pipeline, instruction.strip()):
        stages.write(note)
    first_path = df.write_episode_dataset(out / "first_frame", first)
    stages.update()

    stages.set_postfix_str(f"predict: {instruction!r}")
    pred = predict_episode(pipeline, first, instruction, num_frames=cfg.num_frames, seed=cfg.sample_seed, num_steps=cfg.steps)
    pred_dir = write_prediction(pred, out / "prediction")
    stages.update()

    stages.set_postfix_str("reconstruct")
    recon = reconstruct_episode(pred, config=ReconConfig())
    recon.metadata.update({"instruction": instruction, "task": cfg.task, "seed": cfg.seed})
    recon_dir = recon.save(out / "reconstruction")
    stages.update()

    stages.set_postfix_str("export html")
    html = export_html(recon, out / "scene.html")
    stages.update()
    stages.close()
    (out / "instruction.txt").write_text(instruction + "\n")
    return {
        "first frame": first_path,
        "prediction": pred_dir,
        "reconstruction": recon_dir,
        "html": html,
        "instruction": out / "instruction.txt",
    }
