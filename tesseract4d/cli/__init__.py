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
    "distill": ("tesseract4d.cli.distill", "distil a checkpoint into a few-step student (one network pass per step)"),
    "checkpoint": ("", "checkpoint surgery: export a run, swap a decoder, set sampler defaults"),
    "predict": ("tesseract4d.cli.predict", "predict the RGB-D-N future from a first frame and an instruction"),
    "reconstruct": ("tesseract4d.cli.reconstruct", "fuse an RGB-D-N video into a consistent 4D point cloud"),
    "evaluate": ("tesseract4d.cli.evaluate", "metrics of a prediction/reconstruction against ground truth"),
    "train-idm": ("tesseract4d.cli.train_idm", "train the inverse dynamics model (or its behaviour-cloning twin)"),
    "rollout": ("tesseract4d.cli.rollout", "closed-loop rollouts in ManiSkill with success rates per arm"),
    "view": ("tesseract4d.cli.view", "open a reconstruction, episode or prediction in the browser viewer"),
    "demo": ("tesseract4d.cli.demo", "one command: render a scene, predict two futures from two instructions, reconstruct, view"),
}

# Groups of subcommands: group -> name -> (module, one-line help). `research` holds diagnostics only the
# project's own research uses; the top-level help does not list it.
GROUPS: dict[str, dict[str, tuple[str, str]]] = {
    "checkpoint": {
        "export": ("tesseract4d.cli.export", "export a training run's EMA weights as an inference checkpoint"),
        "swap-decoder": ("tesseract4d.cli.swap_decoder",
                         "put a decoder fine-tuned on a latent checkpoint's latents into a copy of it"),
        "set-sampler": ("tesseract4d.cli.set_sampler",
                        "copy a checkpoint with other default sampler settings (steps, guidance)"),
    },
    "research": {
        "goals": ("tesseract4d.cli.goals", "the held-out goals against `evaluate --heldout` reports, as one Markdown table"),
        "from-truth": ("tesseract4d.cli.from_truth",
                       "held-out evaluation with sampling started part-way from the true future"),
        "phrasings": ("tesseract4d.cli.phrasings", "does a model keep still under every way of saying keep still"),
    },
}
HIDDEN = {"research"}

# Old spellings that keep working for one release (one deprecation line on stderr): old -> new words.
DEPRECATED_COMMANDS: dict[str, tuple[str, ...]] = {
    "swap-decoder": ("checkpoint", "swap-decoder"),
    "set-sampler": ("checkpoint", "set-sampler"),
    "goals": ("research", "goals"),
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
    shown = {name: help_ for name, (_, help_) in SUBCOMMANDS.items() if name not in HIDDEN}
    width = max(len(name) for name in shown)
    lines = "\n".join(f"  {name:<{width}}  {help_}" for name, help_ in shown.items())
    return argparse.ArgumentParser(
        prog="tesseract4d",
        description="tesseract4d: a 4D embodied world model (ManiSkill data -> RGB-D-N diffusion -> 4D point clouds -> browser).",
        epilog=f"subcommands:\n{lines}\n\nRun `tesseract4d SUBCOMMAND --help` for its options.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )


def _group_help(group: str) -> str:
    members = GROUPS[group]
    width = max(len(name) for name in members)
    lines = "\n".join(f"  {name:<{width}}  {help_}" for name, (_, help_) in members.items())
    return (f"usage: tesseract4d {group} SUBCOMMAND [options]\n\nsubcommands:\n{lines}\n\n"
            f"Run `tesseract4d {group} SUBCOMMAND --help` for its options.")


def build_parser(words: tuple[str, ...]):
    """(parser, module) of the subcommand named by ``words`` (``("train",)`` or ``("checkpoint", "export")``)."""
    if len(words) == 2:
        module_name, help_ = GROUPS[words[0]][words[1]]
    else:
        module_name, help_ = SUBCOMMANDS[words[0]]
    module = importlib.import_module(module_name)
    parser = argparse.ArgumentParser(
        prog="tesseract4d " + " ".join(words), description=(module.__doc__ or help_).strip(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    module.add_arguments(parser)
    return parser, module


def every_subcommand() -> list[tuple[str, ...]]:
    """The words of every subcommand, groups' members included (not the deprecated spellings)."""
    out: list[tuple[str, ...]] = []
    for name in list(SUBCOMMANDS) + [g for g in GROUPS if g not in SUBCOMMANDS]:
        if name in GROUPS:
            out.extend((name, member) for member in GROUPS[name])
        else:
            out.append((name,))
    return out


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
    if argv[0] in DEPRECATED_COMMANDS:
        from tesseract4d.cli.config_args import warn_deprecated

        new = DEPRECATED_COMMANDS[argv[0]]
        warn_deprecated(f"`tesseract4d {argv[0]}`", f"`tesseract4d {' '.join(new)}`")
        argv = [*new, *argv[1:]]
    name = argv[0]
    if name not in SUBCOMMANDS and name not in GROUPS:
        top.print_usage(sys.stderr)
        print(f"tesseract4d: unknown subcommand {name!r}; choose one of: "
              f"{', '.join(n for n in SUBCOMMANDS if n not in HIDDEN)}", file=sys.stderr)
        return 2
    words: tuple[str, ...] = (name,)
    if name in GROUPS:
        if len(argv) < 2 or argv[1] in ("-h", "--help"):
            print(_group_help(name), file=sys.stdout if len(argv) >= 2 else sys.stderr)
            return 0 if len(argv) >= 2 else 2
        if argv[1] not in GROUPS[name]:
            print(f"tesseract4d {name}: unknown subcommand {argv[1]!r}; choose one of: {', '.join(GROUPS[name])}",
                  file=sys.stderr)
            return 2
        words = (name, argv[1])
    from tesseract4d import runtime

    runtime.configure()
    parser, module = build_parser(words)
    args = parser.parse_args(argv[len(words):])
    name = " ".join(words)
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

