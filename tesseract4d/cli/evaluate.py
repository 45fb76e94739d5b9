"""Metrics of a prediction or a reconstruction against the ground-truth episode: Chamfer
distance (L1: mean unsquared nearest-neighbour distance, both directions averaged, metres),
depth AbsRel / δ1 / δ2, normal angle mean / median / share under 11.25°, RGB PSNR / SSIM; per
frame and averaged, over all pixels and over the moving region; and, where the ground truth records
its objects' poses, the object layer's tracks against them (per object final / mean position error,
yaw error; the instructed object within 2 cm, the others kept still within 1 cm). Prints a table; --json writes
the report that `tesseract4d view --compare GT --metrics REPORT` shows per frame.

PRED is a reconstruction folder (from `tesseract4d reconstruct`) or an episode (.h5, a
prediction folder holding one episode, or DIR/ENV_ID/SEED), which is back-projected as is.

With --checkpoint and --heldout instead of PRED/--gt, evaluates a model over a held-out dataset:
predicts every episode from its first frame and instruction and scores, in the same run, the
model with the reconstruction's consistency step, the model without it, and the static world
(first frame repeated), over all pixels and the moving region, plus instruction following
(does the instructed object move the right way), object permanence, instruction contrast over
counterfactual groups, instruction discrimination (does each network's one-step prediction from
the scene's noise pick its own instruction's true future among its group's: the words used by the
network, whatever its sampler makes of them) and words over the noisy sample (shown another
instruction's future noised to t = 0.5, does the prediction from its own words still land nearer its
own future?), token grid and edge sharpness, the object layer against the recorded object poses
(instructed object within 2 cm, still objects within 1 cm; the tracker on the truth's own frames as
the ceiling), per skill and per task. Several
--checkpoint options score several models side by side in the same run, also when their
resolutions differ from the data's by a whole factor (the first frame is resized to each model's
resolution and its prediction back; every metric is taken at the data's resolution). Several
--sample-seed values predict every episode once per noise seed and pool the scores: one noise
draw decides much of an instruction's outcome, so compare checkpoints on several. Writes
report.json and report.md (every row explained in docs/evaluation.md) to --out.

With --horizon, --heldout is scored for drift over long rollouts: every episode is predicted at its
own length (a chained episode clip by clip with its instruction schedule) and the model and the
static world are scored frame by frame (moving-region PSNR, depth AbsRel, object permanence, the
object layer's position error), with the first clip's frames set against the last as many frames;
writes horizon.json, horizon.md and horizon.png (the curves) to --out.

Examples:
  tesseract4d evaluate out/recon --gt data/test/episodes/PickCube-v1/seed_100000.h5 --json out/report.json
  tesseract4d evaluate --heldout data/heldout --out outputs/heldout_eval      # the shipped default (v2-2step)
  tesseract4d evaluate --heldout data/heldout_groups --checkpoint tesseract4d/checkpoints/v2 \\
      --checkpoint tesseract4d/checkpoints/v2-2step --sample-seed 0 1 2 --out outputs/heldout_compare
  tesseract4d evaluate --horizon --heldout data/heldout_chained --out outputs/horizon
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from dataclasses import dataclass

from tesseract4d.cli.argument_types import number, seed, whole
from tesseract4d.configs import knob
from tesseract4d.precision import precision_field
from tesseract4d.dataset_format import HELDOUT_SEED_START
from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT


@dataclass
class EvaluateOptions:
    """The options of `evaluate` set with ``--set NAME=VALUE``."""

    max_depth: float | None = knob(None, "evaluation range in metres: depth, normal and Chamfer metrics count only "
                                         "pixels whose true depth is at most this (none: all pixels; held-out "
                                         "evaluation: the checkpoint's depth range)")
    # "default 4" is model/predict.py's DEFAULT_SCENE_BATCH, written out so that --help needs no torch
    # (tests/cli/test_cli_eval_args.py compares the two).
    batch_size: int | None = knob(None, "held-out: scenes predicted together in one network call (default 4; more "
                                        "needs more memory); each scene gets the noise it gets alone")
    text_guidance: float | None = knob(None, "held-out: text guidance scale of the sampler (none: each checkpoint "
                                             "preset's; 1 = no guidance)")
    precision: str = precision_field()
    per_frame: bool = knob(True, "print every frame's metrics, not only the means")


def _options(args: argparse.Namespace) -> EvaluateOptions:
    values = {k: getattr(args, k) for k in ("max_depth", "batch_size", "text_guidance", "precision") if hasattr(args, k)}
    values.update(getattr(args, "set_overrides", None) or {})
    return EvaluateOptions(**values)


class _AppendCheckpoint(argparse.Action):
    """--checkpoint: the shipped model by default (a Path); each use adds one to a list that replaces it."""

    def __call__(self, parser, namespace, values, option_string=None):
        current = getattr(namespace, self.dest)
        setattr(namespace, self.dest, (current if isinstance(current, list) else []) + [values])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from tesseract4d.cli.config_args import PRECISION_MOVED, add_deprecated, add_moved_to_set, add_set_option

    parser.add_argument("pred", nargs="?", help="reconstruction folder, or a predicted episode (.h5 / folder / DIR/ENV_ID/SEED)")
    parser.add_argument("--gt", help="ground-truth episode (.h5 / folder / DIR/ENV_ID/SEED)")
    parser.add_argument("--json", type=Path, metavar="REPORT", help="also write the report as JSON")
    add_heldout_arguments(parser, full=True)
    add_set_option(parser, EvaluateOptions)
    add_moved_to_set(parser, EvaluateOptions, [
        ("--max-depth", "max_depth", number(0, above=True)), ("--batch-size", "batch_size", whole(1)),
        ("--text-guidance", "text_guidance", number(0, above=True, hint=" (1: no guidance)")), PRECISION_MOVED,
        ("--no-per-frame", "per_frame", None, False),
    ])
    add_deprecated(parser, "--start-from-truth", use="`tesseract4d research from-truth --sigma SIGMA`",
                   dest="start_from_truth", type=float, metavar="SIGMA")
    parser.set_defaults(start_from_truth=None)


def add_heldout_arguments(parser: argparse.ArgumentParser, full: bool = False) -> None:
    """The options of held-out evaluation (``full``: also camera, depth range, batch size and text
    guidance, which `research from-truth` leaves at their defaults)."""
    if full:
        parser.add_argument("--camera", help="camera to compare (default: the ground truth's first)")
    else:
        parser.set_defaults(camera=None)
    parser.set_defaults(max_depth=None, batch_size=None, text_guidance=None)
    held = parser.add_argument_group("held-out evaluation of a model" + (" (instead of PRED --gt)" if full else ""))
    held.add_argument("--checkpoint", type=Path, action=_AppendCheckpoint, default=SHIPPED_CHECKPOINT,
                      help="model checkpoint folder (default: the shipped v2-2step); repeat it to score several "
                           "checkpoints side by side with the static world in one report")
    held.add_argument("--heldout", type=Path,
                      help=f"held-out dataset folder (datagen --seed-start {HELDOUT_SEED_START} --instruction-split heldout)")
    held.add_argument("--out", type=Path, help="folder for report.json and report.md")
    if full:
        held.add_argument("--horizon", action="store_true",
                          help="score drift instead: every episode predicted at its own length (with its instruction "
                               "schedule), per-frame curves of the model and the static world; writes horizon.json, "
                               "horizon.md and horizon.png to --out")
    else:
        parser.set_defaults(horizon=False)
    if full:
        held.add_argument("--steps", type=whole(1),
                          help="sampler steps of every checkpoint (default: each checkpoint preset's own, e.g. 2 for a "
                               "distilled student beside 10 for its teacher)")
    else:
        parser.set_defaults(steps=None)
    held.add_argument("--sample-seed", type=seed(), nargs="+", default=[0], metavar="SEED",
                      help="diffusion noise seed (default 0); several (e.g. 0 1 2) predict every episode once per "
                           "seed and pool the scores: one noise draw decides much of an instruction's outcome, so "
                           "compare checkpoints on several")
    if full:
        held.add_argument("--max-per-task", type=whole(1), metavar="N",
                          help="episodes per task at most, a counterfactual group kept whole (default: all)")
    else:
        parser.set_defaults(max_per_task=None)
    parser.set_defaults(precision="auto")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace a --json file / write into an --out folder that this command did not write")


def load_prediction(spec: str):
    """A Recon4D for a reconstruction folder, else the episode ``spec`` names."""
    from reconstruction.recon4d import MANIFEST, Recon4D
    from tesseract4d.dataset_format import read_episode, resolve_episode

    if (Path(spec) / MANIFEST).is_file():
        return Recon4D.load(spec)
    return read_episode(resolve_episode(spec))


def scene_mismatch(pred, gt) -> str | None:
    """A warning when ``pred`` (an Episode or a Recon4D, which record the env id and seed of the
    scene they came from) is of another scene than the ground-truth episode ``gt``; else None."""
    from tesseract4d.dataset_format import Episode

    if isinstance(pred, Episode):
        env_id, scene_seed = pred.env_id, pred.seed
    else:
        env_id, scene_seed = pred.metadata.get("env_id"), pred.metadata.get("seed")
    if env_id is None or scene_seed is None or (env_id, int(scene_seed)) == (gt.env_id, int(gt.seed)):
        return None
    if env_id == "user":  # a first frame from the user's own files (`predict --rgb`) names no scene
        return None
    return (f"warning: the prediction is of {env_id} seed {scene_seed} but the ground truth is of {gt.env_id} seed "
            f"{gt.seed}: the metrics compare two different scenes; pass the ground truth of {env_id} seed "
            f"{scene_seed} as --gt")


def _is_episode_report(path: Path) -> bool:
    """An earlier `evaluate --json` report (safe to replace)."""
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(d, dict) and {"pred", "gt", "num_frames"} <= set(d)


def run_horizon(args: argparse.Namespace) -> int:
    from tesseract4d.errors import UserError
    from tesseract4d.evaluation.horizon import HorizonConfig, evaluate_horizon, format_markdown, write_horizon_report
    from tesseract4d.outputs import OutputDir

    checkpoints = args.checkpoint if isinstance(args.checkpoint, list) else [args.checkpoint]
    if len(checkpoints) != 1 or len(args.sample_seed) != 1:
        raise UserError("--horizon scores one --checkpoint with one --sample-seed; run it once per checkpoint")
    output = None if args.out is None else OutputDir(args.out, "evaluate", inputs=[*checkpoints, args.heldout],
                                                     overwrite=args.overwrite)
    options = _options(args)
    cfg = HorizonConfig(checkpoint=checkpoints[0], data=args.heldout, camera=args.camera, sample_seed=args.sample_seed[0],
                        num_steps=args.steps, batch_size=options.batch_size, max_episodes=args.max_per_task,
                        precision=options.precision, max_depth_m=options.max_depth, text_guidance=options.text_guidance)
    report = evaluate_horizon(cfg)
    return _publish(output, write_horizon_report, report, format_markdown(report),
                    ("horizon.json", "horizon.md", "horizon.png"))


def _publish(output, write, report: dict, text: str, names: tuple[str, ...]) -> int:
    """Write ``report`` through ``output``'s stage (when there is an --out), print ``text`` and the files."""
    if output is not None:
        with output as stage:
            write(report, stage)
    print(text)
    if output is not None:
        files = [str(output.path / n) for n in names]
        print(f"wrote {', '.join(files[:-1])} and {files[-1]}")
    return 0


def run_heldout(args: argparse.Namespace) -> int:
    from tesseract4d.evaluation.heldout import HeldoutConfig, evaluate_heldout, format_markdown, write_heldout_report

    from tesseract4d.outputs import OutputDir

    checkpoints = args.checkpoint if isinstance(args.checkpoint, list) else [args.checkpoint]
    output = None if args.out is None else OutputDir(args.out, "evaluate", inputs=[*checkpoints, args.heldout],
                                                     overwrite=args.overwrite)
    seeds = args.sample_seed[0] if len(args.sample_seed) == 1 else args.sample_seed
    options = _options(args)
    cfg = HeldoutConfig(checkpoint=checkpoints[0] if len(checkpoints) == 1 else checkpoints, data=args.heldout, out=None,
                        camera=args.camera, num_steps=args.steps, sample_seed=seeds, max_episodes=args.max_per_task,
                        max_depth_m=options.max_depth, precision=options.precision, batch_size=options.batch_size,
                        text_guidance=options.text_guidance, start_from_truth=args.start_from_truth)
    report = evaluate_heldout(cfg)
    if args.out is not None:
        report["config"]["out"] = str(args.out)  # written through a stage of its own, not by evaluate_heldout
    return _publish(output, write_heldout_report, report, format_markdown(report), ("report.json", "report.md"))


def run(args: argparse.Namespace) -> int:
    from tesseract4d.evaluation.episode import evaluate_episode, format_report, json_safe
    from tesseract4d.dataset_format import read_episode, resolve_episode
    from tesseract4d.errors import UserError

    if args.horizon and args.heldout is None:
        raise UserError("--horizon scores a held-out dataset: give --heldout DIR (e.g. chained episodes from "
                        "`datagen --set chain_skills=4 --frames 64`) and --out")
    if args.heldout is not None:
        if args.pred is not None:
            raise UserError("held-out evaluation takes --heldout DIR [--checkpoint CKPT] (and no PRED)")
        return run_horizon(args) if args.horizon else run_heldout(args)
    if args.pred is None or args.gt is None:
        raise UserError("give PRED --gt EPISODE, or --checkpoint CKPT --heldout DIR; see `tesseract4d evaluate --help`")

    from tesseract4d.outputs import OutputFile

    output = None
    if args.json:
        output = OutputFile(args.json, inputs=[args.pred, args.gt], overwrite=args.overwrite, flag="--json",
                            is_ours=_is_episode_report)
    pred = load_prediction(args.pred)
    gt_path = resolve_episode(args.gt)
    gt = read_episode(gt_path)
    mismatch = scene_mismatch(pred, gt)
    if mismatch:
        print(mismatch, file=sys.stderr)
    report = evaluate_episode(pred, gt, camera=args.camera, max_depth_m=_options(args).max_depth)
    report.update({"pred": str(args.pred), "gt": str(gt_path)})
    if report["pred_frames"] != report["gt_frames"]:
        print(f"note: prediction has {report['pred_frames']} frames, ground truth {report['gt_frames']}; "
              f"evaluated the first {report['num_frames']}")
    print(format_report(report, per_frame=_options(args).per_frame))
    from tesseract4d.evaluation.object_tracks import episode_object_report, format_rows

    objects = episode_object_report(pred, gt, camera=report["camera"], first_scored_frame=report["first_scored_frame"])
    if objects is not None:
        report["objects"] = objects
        print(format_rows(objects))
    if output is not None:
        with output as tmp:
            tmp.write_text(json.dumps(json_safe(report), indent=2))
        print(f"wrote {args.json}")
    return 0
