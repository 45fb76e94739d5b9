"""The ``tesseract4d`` console entry point.

Each subcommand lives in its own module exposing ``add_arguments(parser)`` and
``run(args) -> int``; only the chosen subcommand's module is imported, so ``--help`` is fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from tesseract4d.errors import Terminated

# name -> (module, one-line help). The order is the data flow.
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "datagen": ("tesseract4d.cli.datagen", "generate RGB-D-N episodes from ManiSkill motion planners"),
    "dataset": ("tesseract4d.cli.dataset", "inspect (info) or validate (check) a dataset folder"),
    "train-autoencoder": ("tesseract4d.cli.train_autoencoder", "train the RGB-D-N autoencoder of the latent model"),
    "encode-latents": ("tesseract4d.cli.encode_latents", "encode a dataset once into a latent cache for the latent model"),
    "train": ("tesseract4d.cli.train", "train the RGB-D-N video diffusion model"),
    "swap-decoder": ("tesseract4d.cli.swap_decoder", "put a decoder fine-tuned on a latent checkpoint's latents into a copy of it"),
    "set-sampler": ("tesseract4d.cli.set_sampler", "copy a checkpoint with other default sampler settings (steps, guidance)"),
    "distill": ("tesseract4d.cli.distill", "distil a checkpoint into a few-step student (one network pass per step)"),
    "predict": ("tesseract4d.cli.predict", "predict the RGB-D-N future from a first frame and an instruction"),
    "reconstruct": ("tesseract4d.cli.reconstruct", "fuse an RGB-D-N video into a consistent 4D point cloud"),
    "evaluate": ("tesseract4d.cli.evaluate", "metrics of a prediction/reconstruction against ground truth"),
    "goals": ("tesseract4d.cli.goals", "the held-out goals against `evaluate --heldout` reports, as one Markdown table"),
    "train-idm": ("tesseract4d.cli.train_idm", "train the inverse dynamics model (or its behaviour-cloning twin)"),
    "rollout": ("tesseract4d.cli.rollout", "closed-loop rollouts in ManiSkill with success rates per arm"),
    "view": ("tesseract4d.cli.view", "open a reconstruction, episode or prediction in the browser viewer"),
    "demo": ("tesseract4d.cli.demo", "one command: render a scene, predict two futures from two instructions, reconstruct, view"),
}


def _raise_terminated(signum, frame) -> None:
    raise Terminated()


def _stop_cleanly_on_sigterm():
    """Install the SIGTERM handler for one command (main thread only); returns the previous handler."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, _raise_terminated)


def _top_parser() -> argparse.ArgumentParser:
    width = max(len(name) for name in SUBCOMMANDS)
    lines = "\n".join(f"  {name:<{width}}  {help_}" for name, (_, help_) in SUBCOMMANDS.items())
    return argparse.ArgumentParser(
        prog="tesseract4d",
        description="tesseract4d: a 4D embodied world model (ManiSkill data -> RGB-D-N diffusion -> 4D point clouds -> browser).",
        epilog=f"subcommands:\n{lines}\n\nRun `tesseract4d SUBCOMMAND --help` for its options.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    top = _top_parser()
    top.add_argument("--version", action="store_true", help="print the version and exit")
    if not argv or argv[0] in ("-h", "--help"):
        top.print_help()
        return 0
    if argv[0] == "--version":
        from tesseract4d import __version__

        print(__version__)
        return 0
    name = argv[0]
    if name not in SUBCOMMANDS:
        top.print_usage(sys.stderr)
        print(f"tesseract4d: unknown subcommand {name!r}; choose one of: {', '.join(SUBCOMMANDS)}", file=sys.stderr)
        return 2
    from tesseract4d import runtime

    runtime.configure()
    module_name, help_ = SUBCOMMANDS[name]
    module = importlib.import_module(module_name)
    parser = argparse.ArgumentParser(
        prog=f"tesseract4d {name}", description=(module.__doc__ or help_).strip(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    module.add_arguments(parser)
    args = parser.parse_args(argv[1:])
    previous = _stop_cleanly_on_sigterm()
    try:
        return int(module.run(args) or 0)
    except Terminated:
        print("\nterminated; finished work is kept on disk", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print("\ninterrupted; finished work is kept on disk", file=sys.stderr)
        return 130
    except BrokenPipeError:  # stdout closed by its reader (`... | head`): stop quietly, as Unix tools do
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error when Python flushes
        return 141
    except Exception as e:  # user-facing errors: one clear line, no traceback
        from tesseract4d.errors import UserError

        if isinstance(e, UserError):
            print(f"tesseract4d {name}: error: {e}", file=sys.stderr)
            return 2
        if isinstance(e, PermissionError):
            print(f"tesseract4d {name}: error: permission denied: {e.filename}; choose paths this user can write",
                  file=sys.stderr)
            return 2
        raise
    finally:
        if previous is not None:
            import signal

            signal.signal(signal.SIGTERM, previous)

