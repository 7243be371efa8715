"""Frozen dataclass configs with documented fields, turned into command-line flags.

Every config field is declared with `option(default, "one-line doc")`; the doc becomes the
flag's `--help` text. Nested configs become dotted flags: `SlamConfig.tracker.iters` is
`--tracker.iters`. Defaults live only in the dataclasses; presets are named instances.
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from typing import Any, TypeVar

T = TypeVar("T")


def option(default: Any, doc: str) -> Any:
    """A config field with its default and a one-line doc (the `--help` text)."""
    return dataclasses.field(default=default, metadata={"doc": doc})


def section(factory: type, doc: str) -> Any:
    """A nested config field (its own fields become dotted flags)."""
    return dataclasses.field(default_factory=factory, metadata={"doc": doc})


def _leaf_fields(cfg: Any, prefix: str = ""):
    hints = typing.get_type_hints(type(cfg))
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        name = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            yield from _leaf_fields(value, name + ".")
        else:
            yield name, hints[f.name], value, f.metadata.get("doc", "")


def _parse(kind: Any, text: str) -> Any:
    origin = typing.get_origin(kind)
    args = typing.get_args(kind)
    if origin in (typing.Union, types.UnionType):
        if text.lower() in ("none", ""):
            return None
        return _parse(next(a for a in args if a is not type(None)), text)
    if origin is typing.Literal:
        if text not in args:
            raise ValueError(f"expected one of {', '.join(map(str, args))}, got {text!r}")
        return text
    if origin is tuple:
        item = args[0]
        return tuple(_parse(item, part) for part in text.split(",") if part.strip())
    if kind is bool:
        if text.lower() in ("1", "true", "yes", "on"):
            return True
        if text.lower() in ("0", "false", "no", "off"):
            return False
        raise ValueError(f"expected true or false, got {text!r}")
    return kind(text)


def _show(value: Any) -> str:
    if isinstance(value, tuple):
        return ",".join(str(v) for v in value)
    return str(value)


def add_config_arguments(parser: argparse.ArgumentParser, defaults: Any, title: str) -> None:
    """One `--a.b` flag per leaf field of `defaults` (values are parsed later, per preset)."""
    group = parser.add_argument_group(title, "per-field overrides of the chosen preset")
    for name, kind, value, doc in _leaf_fields(defaults):
        metavar = getattr(kind, "__name__", "VALUE").upper()
        if typing.get_origin(kind) is tuple:
            metavar = "A,B,..."
        elif typing.get_origin(kind) is typing.Literal:
            metavar = "{" + ",".join(map(str, typing.get_args(kind))) + "}"
        group.add_argument(
            f"--{name}",
            dest=f"cfg:{name}",
            default=None,
            metavar=metavar,
            help=f"{doc} (default: {_show(value)})",
        )


def overrides_from_args(args: argparse.Namespace) -> dict[str, str]:
    """The `--a.b VALUE` flags a user actually gave."""
    return {k[4:]: v for k, v in vars(args).items() if k.startswith("cfg:") and v is not None}


def apply_overrides(cfg: T, overrides: dict[str, str]) -> T:
    """A copy of `cfg` with dotted fields replaced by parsed text values.

    Raises:
        ValueError: naming the field for an unknown name or a value of the wrong type.
    """
    known = {name: kind for name, kind, _, _ in _leaf_fields(cfg)}
    changes = _Section()
    for name, text in overrides.items():
        if name not in known:
            raise ValueError(f"unknown setting {name!r}")
        try:
            value = _parse(known[name], text)
        except (ValueError, TypeError, StopIteration) as e:
            raise ValueError(f"--{name}: cannot use {text!r} ({e})") from None
        *sections, leaf = name.split(".")
        inner = changes
        for part in sections:
            inner = inner.setdefault(part, _Section())
        inner[leaf] = value
    return _replaced(cfg, changes)


class _Section(dict):
    """New values of some fields of one config section (nested sections: `_Section`s)."""


def _replaced(cfg: Any, changes: _Section) -> Any:
    """`cfg` with `changes`: each section is made once with all its new values, so that its
    checks (`__post_init__`) see settings that only go together, in any order given."""
    fields = {
        k: _replaced(getattr(cfg, k), v) if isinstance(v, _Section) else v
        for k, v in changes.items()
    }
    return dataclasses.replace(cfg, **fields)


def overrides_or_exit(
    parser: argparse.ArgumentParser, cfg: T, overrides: dict[str, str], what: str = ""
) -> T:
    """`apply_overrides` for a command line: an unknown key or a wrong value ends the program
    with `parser`'s usage error (exit status 2, `what` before the message), not a traceback."""
    try:
        return apply_overrides(cfg, overrides)
    except ValueError as e:
        parser.error(f"{what}{e}")


def setting(text: str) -> tuple[str, str]:
    """One `KEY=VALUE` text, as a benchmark's `--set` takes it: `(key, value)` for
    `apply_overrides` (the argparse `type=` of such flags; `dict()` of their list is the
    overrides).

    Raises:
        argparse.ArgumentTypeError: no `=`, or nothing before it.
    """
    key, eq, value = text.partition("=")
    if not eq or not key.strip():
        raise argparse.ArgumentTypeError(f"want KEY=VALUE, got {text!r}")
    return key.strip(), value.strip()


def to_dict(cfg: Any) -> dict:
    """Plain nested dict of a config (tuples as lists), for config.json."""
    return dataclasses.asdict(cfg)


def flat_settings(settings: dict, prefix: str = "") -> dict[str, str]:
    """`to_dict` output (or config.json) as `{"section.field": "text"}`, the inverse of
    `apply_overrides`' input: tuples as `a,b,c`."""
    flat: dict[str, str] = {}
    for key, value in settings.items():
        if isinstance(value, dict):
            flat.update(flat_settings(value, f"{prefix}{key}."))
        elif isinstance(value, list | tuple):
            flat[f"{prefix}{key}"] = ",".join(str(v) for v in value)
        else:
            flat[f"{prefix}{key}"] = str(value)
    return flat
