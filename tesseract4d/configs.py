"""Option dataclasses saved next to their outputs: one way to write them as JSON, to read a folder
option that takes one folder or several, and to override a field by name from text.

A config field is written once, with its default and one line of help::

    lr: float | None = knob(None, "peak learning rate (default: the preset's)")

The command line derives its flags from these fields (``tesseract4d.cli.config_args``); the fields
that are not flags stay reachable as ``--set NAME=VALUE``, typed from the field's annotation by
:func:`parse_field_value` and applied by :func:`with_overrides`.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from pathlib import Path
from typing import Any

from tesseract4d.errors import UserError

_NONE_WORDS = ("none", "null")
_TRUE_WORDS = ("1", "true", "yes", "on")
_FALSE_WORDS = ("0", "false", "no", "off")


def knob(default: Any = dataclasses.MISSING, help: str = "", *, default_factory: Any = dataclasses.MISSING,
         **extra: Any) -> Any:
    """A dataclass field with its one-line help (shown by ``--help`` and ``--set list``); ``extra`` goes
    into the metadata too (``metavar``, ``choices``)."""
    return dataclasses.field(default=default, default_factory=default_factory, metadata={"help": help, **extra})


def plain(value):
    """``value`` with Paths as strings, inside lists and tuples too (JSON-ready)."""
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    return value


def config_dict(config) -> dict:
    """A dataclass of options as a JSON-ready dict."""
    return {k: plain(v) for k, v in dataclasses.asdict(config).items()}


def folder_list(value) -> list[Path]:
    """One folder, several, or None as a list of Paths."""
    if value is None:
        return []
    return [Path(v) for v in value] if isinstance(value, (list, tuple)) else [Path(value)]


# --------------------------------------------------------------------------- fields by name


def field_types(cls) -> dict[str, Any]:
    """Each field's resolved annotation (the modules use ``from __future__ import annotations``)."""
    return typing.get_type_hints(cls)


def field_help(f: dataclasses.Field) -> str:
    return f.metadata.get("help", "")


def field_default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def _members(annotation) -> tuple[list, bool]:
    """The non-None members of a union annotation (or the annotation alone) and whether None is allowed."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = typing.get_args(annotation)
        return [a for a in args if a is not type(None)], type(None) in args
    return [annotation], annotation is type(None)


def type_name(annotation) -> str:
    members, optional = _members(annotation)
    names = []
    for a in members:
        origin = typing.get_origin(a)
        if origin is typing.Literal:
            names.append("|".join(map(str, typing.get_args(a))))
        elif origin in (list, tuple):
            names.append("comma-separated list")
        elif origin is dict:
            names.append("k=v,k=v")
        else:
            names.append(getattr(a, "__name__", str(a)))
    return " or ".join(names + (["none"] if optional else []))


def _parse_one(text: str, annotation) -> Any:
    origin = typing.get_origin(annotation)
    if origin is typing.Literal:
        for choice in typing.get_args(annotation):
            if text == str(choice):
                return choice
        raise ValueError
    if origin in (list, tuple):
        (inner, *_) = typing.get_args(annotation) or (str,)
        items = [_parse_one(t.strip(), inner) for t in text.split(",") if t.strip()]
        return items if origin is list else tuple(items)
    if origin is dict:
        key_type, value_type = typing.get_args(annotation) or (str, str)
        pairs = [item.split("=", 1) for item in text.split(",") if item.strip()]
        if any(len(p) != 2 for p in pairs):
            raise ValueError
        # float values as written, nan included: the config's validate() names the bad entry
        parse_value = float if value_type is float else (lambda t: _parse_one(t, value_type))
        return {_parse_one(k.strip(), key_type): parse_value(v.strip()) for k, v in pairs}
    if annotation is bool:
        if text.lower() in _TRUE_WORDS:
            return True
        if text.lower() in _FALSE_WORDS:
            return False
        raise ValueError
    if annotation is int:
        return int(text)
    if annotation is float:
        value = float(text)
        if not math.isfinite(value):
            raise ValueError
        return value
    if annotation in (str, Path):
        return annotation(text)
    if annotation is Any or annotation is dict:
        return text
    raise ValueError


def parse_field_value(cls, name: str, text: str) -> Any:
    """``text`` as a value of field ``name`` of dataclass ``cls`` (its annotation decides the type);
    UserError naming the expected type otherwise."""
    annotation = field_types(cls)[name]
    members, optional = _members(annotation)
    if optional and text.strip().lower() in _NONE_WORDS:
        return None
    choices = next(f for f in dataclasses.fields(cls) if f.name == name).metadata.get("choices")
    for member in members:
        try:
            value = _parse_one(text, member)
        except (TypeError, ValueError):
            continue
        if choices is not None and value not in choices:
            raise UserError(f"--set {name}={text}: choose one of {', '.join(map(str, choices))}")
        return value
    raise UserError(f"--set {name}={text}: expected {type_name(annotation)}")


def settable_fields(cls) -> dict[str, tuple[type, dataclasses.Field, tuple[str, ...]]]:
    """Every field reachable by name, as (owning dataclass, field, path): ``cls``'s own and those of its
    dataclass-valued fields (a nested name is reachable as ``inner.name`` and, unless ``cls`` itself or
    an earlier nested dataclass has the name, as ``name``)."""
    out: dict[str, tuple[type, dataclasses.Field, tuple[str, ...]]] = {}
    nested: dict[str, tuple[type, dataclasses.Field, tuple[str, ...]]] = {}
    types_ = field_types(cls)
    for f in dataclasses.fields(cls):
        if not f.init or f.metadata.get("internal"):  # set by the program, not an option
            continue
        inner = types_[f.name]
        if dataclasses.is_dataclass(inner):
            for g in dataclasses.fields(inner):
                if g.init and not g.metadata.get("internal"):
                    nested[f"{f.name}.{g.name}"] = (inner, g, (f.name, g.name))
        else:
            out[f.name] = (cls, f, (f.name,))
    for dotted, entry in nested.items():
        out[dotted] = entry
        short = dotted.split(".", 1)[1]
        if short not in out:  # the first nested dataclass that has the name owns its short form
            out[short] = entry
    return out


def _listed(fields: dict) -> list[str]:
    """The names to show: each field once, by its short name where it has one."""
    names = []
    for name, entry in fields.items():
        path = entry[2]
        if len(path) == 1 or name == path[-1] or fields.get(path[-1]) is not entry:
            names.append(name)
    return sorted(names)


def with_overrides(config, overrides: dict[str, Any]):
    """A copy of dataclass ``config`` with ``overrides`` (field name -> value, or text to parse by the
    field's type) applied; a name that is not a field is refused with the list of valid ones."""
    if not overrides:
        return config
    fields = settable_fields(type(config))
    for name in overrides:
        if name not in fields:
            raise UserError(f"--set {name}: no such option of {type(config).__name__}; valid names: "
                            f"{', '.join(_listed(fields))}")
    top: dict[str, Any] = {}
    inner: dict[str, dict[str, Any]] = {}
    for name, value in overrides.items():
        owner, f, path = fields[name]
        if isinstance(value, str):
            value = parse_field_value(owner, f.name, value)
        if len(path) == 1:
            top[f.name] = value
        else:
            inner.setdefault(path[0], {})[f.name] = value
    for parent, values in inner.items():
        top[parent] = dataclasses.replace(getattr(config, parent), **values)
    return dataclasses.replace(config, **top)


def describe_fields(cls, names: typing.Iterable[str] | None = None) -> str:
    """One line per settable field: name, type, default and help (what ``--set list`` prints)."""
    fields = settable_fields(cls)
    lines = []
    for name in (_listed(fields) if names is None else names):
        owner, f, _ = fields[name]
        default = field_default(f)
        lines.append(f"  {name} = {plain(default)!r}  ({type_name(field_types(owner)[f.name])})"
                     + (f"  {field_help(f)}" if field_help(f) else ""))
    return "\n".join(lines)
