"""Open a reconstruction, a dataset episode or a prediction in the browser viewer.

PATH is a reconstruction folder (from `tesseract4d reconstruct`), an episode .h5 file, a dataset
or prediction folder holding one episode, DIR/ENV_ID/SEED, or DIR/ENV_ID/SEED_kK (future K of a
counterfactual group). Episodes are back-projected on the fly. The command prints the URL and serves until Ctrl-C; with --export it writes a standalone
HTML recording instead (it opens from disk, no server needed) and exits.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from dataclasses import dataclass

from tesseract4d.cli.argument_types import whole
from tesseract4d.cli.config_args import PRECISION_MOVED, add_moved_to_set, add_set_option, dataclass_from_args
from tesseract4d.configs import knob
from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT
from tesseract4d.precision import precision_field
from viewer.scene import DEFAULT_MAX_POINTS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", help="reconstruction folder, episode .h5, dataset/prediction folder, DIR/ENV_ID/SEED or DIR/ENV_ID/SEED_kK")
    parser.add_argument("--host", default="127.0.0.1", help="address to serve on (default %(default)s; 0.0.0.0 for all)")
    parser.add_argument("--port", type=whole(0, 65535), default=8080, help="port to serve on (default %(default)s)")
    parser.add_argument("--export", type=Path, metavar="HTML", help="write a standalone HTML recording to this file and exit")
    parser.add_argument("--compare", metavar="GT_PATH", help="ground truth of the same episode, shown beside PATH")
    parser.add_argument("--labels", nargs=2, metavar=("LEFT", "RIGHT"),
                        help="names drawn above the two point clouds of compare mode, e.g. two instructions "
                             "(default: prediction, ground truth)")
    parser.add_argument("--metrics", type=Path, metavar="REPORT_JSON",
                        help="per-frame metrics from `tesseract4d evaluate` for compare mode (default: cheap image metrics)")
    parser.add_argument("--checkpoint", type=Path, default=SHIPPED_CHECKPOINT,
                        help="model checkpoint of the served viewer's Generate panel (not used by --export; default: the shipped v2-2step, tesseract4d/checkpoints/v2-2step; tesseract4d/checkpoints/v2 is its 10-step teacher)")
    parser.add_argument("--camera", help="which camera of an episode to show (default: the first)")
    parser.add_argument("--overwrite", action="store_true", help="with --export: replace a file that is not an earlier export")
    add_set_option(parser, ViewOptions)
    add_moved_to_set(parser, ViewOptions, [("--max-points", "max_points", whole(1)), PRECISION_MOVED])


@dataclass
class ViewOptions:
    """The options of `view` set with ``--set NAME=VALUE``."""

    max_points: int = knob(DEFAULT_MAX_POINTS, "point budget per frame sent to the browser")
    precision: str = precision_field()  # of the Generate panel's model


def run(args: argparse.Namespace) -> int:
    from tesseract4d.errors import UserError

    options = dataclass_from_args(ViewOptions, args)
    if args.export is not None:
        served_only = [flag for flag, value in (("--compare", args.compare), ("--labels", args.labels),
                                                ("--metrics", args.metrics)) if value is not None]
        if served_only:
            raise UserError(f"--export records PATH alone (no compare mode), so it cannot use "
                            f"{', '.join(served_only)}; drop them, or serve the viewer without --export to compare")
        from viewer.export import export_html
        from viewer.sources import load_source

        from tesseract4d.outputs import OutputFile
        from viewer.export import is_export

        inputs = [args.path]
        try:
            from tesseract4d.dataset_format import resolve_episode

            inputs.append(resolve_episode(args.path))  # DIR/ENV_ID/SEED names a file
        except UserError:
            pass  # a reconstruction folder or a path load_source reports on
        OutputFile(args.export, inputs=inputs, overwrite=args.overwrite, flag="--export", is_ours=is_export)
        out = export_html(load_source(args.path, camera=args.camera), args.export, max_points=options.max_points,
                          inputs=tuple(inputs), overwrite=args.overwrite)
        print(f"wrote {out} (open it in a browser; no server needed)")
        return 0
    from viewer.app import ViewerApp, serve_forever

    if args.labels and args.compare is None:
        raise UserError("--labels names the two point clouds of compare mode: pass --compare PATH too")
    if args.metrics is not None and args.compare is None:
        raise UserError("--metrics shows per-frame metrics in compare mode: pass --compare GT_PATH (the ground truth "
                        "the report was made against) too")
    labels = {"labels": tuple(args.labels)} if args.labels else {}
    app = ViewerApp.from_path(args.path, compare=args.compare, metrics=args.metrics, checkpoint=args.checkpoint, **labels,
                              precision=options.precision, camera=args.camera, host=args.host, port=args.port,
                              max_points=options.max_points)
    serve_forever(app)
    return 0
