"""Command-line flags derived from config dataclasses, ``--set NAME=VALUE`` overrides, named recipes
and the deprecated spellings of renamed flags.

A config field carries its default and one line of help (``tesseract4d.configs.knob``); a subcommand
names the few fields that are flags and gets the rest as ``--set`` overrides, typed from each field's
annotation and checked at parse time (an unknown name is refused with the valid ones)::

    add_field_flags(parser, TrainConfig, ["data", "out", "max_steps"])
    add_set_option(parser, TrainConfig)
    add_recipe_options(parser, RECIPES)
    ...
    cfg = config_from_args(TrainConfig, args, recipe=recipe_from_args(args, RECIPES, read_recipe))

Precedence: the dataclass default < the recipe < ``--set`` < an explicit flag.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import typing
from pathlib import Path
from typing import Any, Callable, Iterable

from tesseract4d.configs import (
    _members, describe_fields, field_default, field_help, field_types, parse_field_value, plain, settable_fields,
)
from tesseract4d.errors import UserError

SET_DEST = "set_overrides"
# How --help names the value of the trainers' common fields (their metadata may name it otherwise).
METAVARS = {"max_steps": "N|auto", "max_minutes": "M", "ckpt_every": "N", "data": "DIR", "pairs.data": "DIR",
            "heldout": "DIR", "out": "RUN", "student.out": "RUN", "pairs.out": "PAIRS", "init": "CKPT",
            "teacher": "CKPT", "autoencoder": "DIR", "predicted_futures": "CKPT"}


def deprecation_line(old: str, new: str) -> str:
    """The one line a deprecated spelling prints on stderr."""
    return f"tesseract4d: {old} is deprecated and goes away in the next release; use {new}"


def warn_deprecated(old: str, new: str) -> None:
    print(deprecation_line(old, new), file=sys.stderr)


# --------------------------------------------------------------------------- flags from fields


def _flag_type(cls, name: str, annotation=None) -> Callable[[str], Any]:
    """argparse type of field ``name``: its annotation's parse, refusals in argparse's words."""
    def parse(text: str):
        try:
            return parse_field_value(cls, name, text)
        except UserError as e:
            raise argparse.ArgumentTypeError(f"{str(e).split(': ', 1)[-1]}, got {text!r}") from None

    parse.__name__ = "value"
    return parse


def _default_text(value) -> str:
    value = plain(value)
    if value is None or value == "":
        return ""
    if isinstance(value, bool):
        return ""
    if isinstance(value, list):
        value = ",".join(map(str, value))
    return f" (default {value})"


def add_field_flags(parser, cls, names: Iterable[str], *, types: dict[str, Callable] | None = None,
                    flags: dict[str, str] | None = None, required: Iterable[str] = ()) -> None:
    """One flag per named field of ``cls``: ``--field-name``, its help and default from the field, its
    type from the annotation (or ``types[name]``, a parse-time check such as ``whole(1)``). Unset
    flags parse to None, so a recipe or ``--set`` below them stands. A bool field is a switch that sets
    the opposite of its default; ``flags`` renames (``{"steps": "--max-steps"}``)."""
    types, flags, required = types or {}, flags or {}, set(required)
    fields = settable_fields(cls)
    for name in names:
        owner, f, _ = fields[name]
        annotation = field_types(owner)[f.name]
        flag = flags.get(name, "--" + name.replace("_", "-"))
        help_ = field_help(f).replace("%", "%%")
        members, _optional = _members(annotation)
        default = field_default(f)
        kwargs: dict[str, Any] = {"dest": name, "default": None}
        if members == [bool]:
            kwargs.update(action="store_const", const=not bool(default))
            help_ = f.metadata.get("flag_help", help_).replace("%", "%%")
        else:
            if f.metadata.get("show_default", True) and members[0] is not Path:  # a folder is named, not defaulted
                help_ += _default_text(default)
            origin = typing.get_origin(members[0])
            lists = [m for m in members if typing.get_origin(m) is list]
            if lists and name not in types:
                (inner,) = typing.get_args(lists[0]) or (str,)
                kwargs.update(nargs="+", type=inner if inner in (Path, str, int, float) else str)
            elif origin is typing.Literal:
                kwargs.update(choices=list(typing.get_args(members[0])))
            else:
                kwargs["type"] = types.get(name) or (Path if members[0] is Path else _flag_type(owner, f.name, annotation))
            for key in ("metavar", "choices"):
                if key in f.metadata:
                    kwargs[key] = f.metadata[key]
            if "metavar" not in kwargs and name in METAVARS:
                kwargs["metavar"] = METAVARS[name]
            if name in required:
                kwargs["required"] = True
        parser.add_argument(flag, help=help_, **kwargs)


class _SetAction(argparse.Action):
    """``--set NAME=VALUE``: typed and checked now; ``--set list`` prints the fields and exits."""

    def __init__(self, option_strings, dest, config_class=None, **kwargs):
        self.config_class = config_class
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, value, option_string=None):
        if value in ("list", "help"):
            print(f"fields of {self.config_class.__name__} (set with --set NAME=VALUE):")
            print(describe_fields(self.config_class))
            parser.exit(0)
        name, sep, text = value.partition("=")
        if not sep or not name:
            parser.error(f"--set takes NAME=VALUE, got {value!r} (`--set list` shows the names)")
        store_override(parser, namespace, self.config_class, name.strip(), text)


def store_override(parser, namespace, cls, name: str, value) -> None:
    """Record ``name = value`` (text is parsed by the field's type) in the namespace's overrides; a
    parse error ends the command the way argparse does (usage, one line, exit 2)."""
    fields = settable_fields(cls)
    if name not in fields:
        from tesseract4d.configs import _listed

        parser.error(f"--set {name}: no such option; valid names: {', '.join(_listed(fields))}")
    owner, f, _ = fields[name]
    if isinstance(value, str):
        try:
            value = parse_field_value(owner, f.name, value)
        except UserError as e:
            parser.error(str(e))
    overrides = dict(getattr(namespace, SET_DEST, None) or {})
    overrides[name] = value
    setattr(namespace, SET_DEST, overrides)


def add_set_option(parser, cls) -> None:
    """``--set NAME=VALUE`` (repeatable) over every field of ``cls``."""
    parser.add_argument("--set", action=_SetAction, config_class=cls, dest=SET_DEST, default={},
                        metavar="NAME=VALUE",
                        help="override any option of the config (repeatable; research knobs live here); "
                             "`--set list` prints every name with its default and help")


# --------------------------------------------------------------------------- deprecated spellings


class _Deprecated(argparse.Action):
    """A hidden old spelling: one deprecation line on stderr, then what the new spelling does."""

    def __init__(self, option_strings, dest, use="", config_class=None, set_field=None, **kwargs):
        self.use, self.config_class, self.set_field = use, config_class, set_field
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, value, option_string=None):
        warn_deprecated(option_string, self.use)
        if self.nargs == 0:
            value = self.const
        if self.set_field is not None:
            store_override(parser, namespace, self.config_class, self.set_field, value)
        else:
            setattr(namespace, self.dest, value)


def add_deprecated(parser, old: str, *, use: str, dest: str | None = None, set_field: str | None = None,
                   config_class=None, switch: Any = dataclasses.MISSING, **kwargs) -> None:
    """Keep ``old`` working for one release, hidden from --help: it prints one deprecation line naming
    ``use`` and then stores into ``dest`` (the new flag's) or, with ``set_field``, into the ``--set``
    overrides of ``config_class``. ``switch``: the old spelling takes no value and stores this."""
    extra: dict[str, Any] = dict(kwargs)
    if switch is not dataclasses.MISSING:
        extra.update(nargs=0, const=switch)
    if set_field is not None:
        dest = SET_DEST
        extra.setdefault("default", argparse.SUPPRESS)
    else:
        extra.setdefault("default", argparse.SUPPRESS)
    parser.add_argument(old, action=_Deprecated, dest=dest, use=use, config_class=config_class,
                        set_field=set_field, help=argparse.SUPPRESS, **extra)


# --------------------------------------------------------------------------- recipes


def add_recipe_options(parser, recipes: dict[str, dict], what: str = "training") -> None:
    """``--recipe NAME`` (a named config) and ``--recipe-from CHECKPOINT`` (the recipe it records)."""
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--recipe", choices=sorted(recipes), metavar="NAME",
                       help=f"start from a named {what} recipe ({', '.join(sorted(recipes))}); flags and --set "
                            "change it")
    group.add_argument("--recipe-from", type=Path, metavar="CKPT",
                       help=f"start from the {what} recipe that checkpoint CKPT records; flags and --set change it")


def recipe_from_args(args, recipes: dict[str, dict], read_checkpoint: Callable[[Path], dict]) -> dict:
    """The chosen recipe's field values ({} without --recipe/--recipe-from)."""
    if getattr(args, "recipe", None):
        return dict(recipes[args.recipe])
    if getattr(args, "recipe_from", None) is not None:
        return dict(read_checkpoint(args.recipe_from))
    return {}


def config_from_args(cls, args, names: Iterable[str], *, recipe: dict | None = None, base=None, **fixed):
    """``cls`` from its defaults (or ``base``), then the recipe, ``--set`` and the flags actually given
    (each later one wins), then ``fixed`` (values the command resolved itself)."""
    from tesseract4d.configs import with_overrides

    overrides: dict[str, Any] = dict(recipe or {})
    overrides.update(getattr(args, SET_DEST, None) or {})
    overrides.update({n: getattr(args, n) for n in names if getattr(args, n, None) is not None})
    overrides.update(fixed)
    return with_overrides(base if base is not None else cls(), overrides)


def add_moved_to_set(parser, cls, moved: Iterable[tuple]) -> None:
    """Old flags whose options are ``--set`` fields of ``cls`` now: each ``(old, field)``,
    ``(old, field, type)``, ``(old, field, {argparse keywords})`` or ``(old, field, None, switch_value)``
    keeps working for one release."""
    for old, name, *rest in moved:
        kind = rest[0] if rest else None
        if len(rest) > 1:
            add_deprecated(parser, old, use=f"--set {name}={str(rest[1]).lower()}", set_field=name,
                           config_class=cls, switch=rest[1])
        else:
            extra = kind if isinstance(kind, dict) else {"type": kind} if kind is not None else {}
            if "type" not in extra and "choices" not in extra:
                owner, f, _ = settable_fields(cls)[name]
                extra["type"] = _flag_type(owner, f.name)
            add_deprecated(parser, old, use=f"--set {name}=VALUE", set_field=name, config_class=cls, **extra)


PRECISION_MOVED = ("--precision", "precision", {"choices": ("auto", "fp32", "bf16")})


def dataclass_from_args(cls, args, **given):
    """``cls`` from the namespace's attributes of the same names (absent ones keep their defaults),
    ``given`` values, then the ``--set`` overrides."""
    from tesseract4d.configs import with_overrides

    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if f.init and hasattr(args, f.name)}
    values.update(given)
    return with_overrides(cls(**values), getattr(args, SET_DEST, None) or {})


def add_trainer_options(parser, cls, names: Iterable[str], recipes: dict[str, dict], *,
                        types: dict[str, Callable] | None = None, flags: dict[str, str] | None = None,
                        required: Iterable[str] = (), loop: Iterable[str] = ("max_steps", "max_minutes", "resume",
                                                                             "quiet", "ckpt_every")) -> list[str]:
    """The flags every trainer shares (``--recipe``, ``--recipe-from``, ``--max-steps``, ``--max-minutes``,
    ``--resume``, ``--quiet``, ``--ckpt-every``, ``--set``) after its own ``names``, all derived from
    ``cls``; returns the field names that are flags (for :func:`config_from_args`)."""
    from tesseract4d.training.schedule import max_steps_argument

    fields = [*names, *loop]
    # max_minutes as a plain float, as before: the config's validate() names a non-finite budget
    add_field_flags(parser, cls, fields, types={"max_steps": max_steps_argument, "max_minutes": float, **(types or {})},
                    flags=flags, required=required)
    add_recipe_options(parser, recipes)
    add_set_option(parser, cls)
    add_deprecated(parser, "--no-progress", use="--quiet", dest="quiet", switch=True)
    return fields
