"""Input validation at public boundaries: one helper family that names expected vs actual."""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch


class ShapeError(ValueError):
    """A tensor argument has the wrong shape."""


class InputError(ValueError):
    """Bad user input (file, field, camera) with a message that names it."""


def check_shape(x: torch.Tensor, shape: Sequence[int | str | None], name: str) -> None:
    """Check ``x.shape`` against ``shape``.

    ``shape`` entries: an int (that size), a str (a named size, only reported), ``None`` (any size),
    and a leading ``"..."`` allows any number of leading dimensions.

    Raises:
        ShapeError: naming ``name``, the expected and the actual shape.
    """
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    spec = list(shape)
    leading = bool(spec) and spec[0] == "..."
    if leading:
        spec = spec[1:]
    actual = tuple(x.shape)
    ok = len(actual) >= len(spec) if leading else len(actual) == len(spec)
    if ok:
        tail = actual[len(actual) - len(spec):] if spec else ()
        ok = all(not isinstance(e, int) or e == a for e, a in zip(spec, tail))
    if not ok:
        want = ", ".join(str(e) if e is not None else "*" for e in shape)
        raise ShapeError(f"{name}: expected shape ({want}), got {actual}")


def check_finite(x: torch.Tensor, name: str) -> None:
    """Raise ``InputError`` if ``x`` holds NaN or inf, saying how many."""
    bad = ~torch.isfinite(x)
    if bool(bad.any()):
        raise InputError(f"{name}: {int(bad.sum())} of {x.numel()} values are NaN or infinite")


def check_file(path: str | Path, what: str) -> Path:
    """Return ``path`` as a Path if it is an existing file, else raise ``InputError`` naming it."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{what} not found: {p}" if not p.exists() else f"{what} is not a file: {p}")
    return p


def config_section(cls: type, doc: Any, source: str, section: str, hint: str = "") -> dict[str, Any]:
    """A config file's ``section`` (a YAML mapping, None: empty) checked against the dataclass ``cls``'s fields:
    a copy of it, or ``InputError`` naming ``source`` and the section for a non-mapping (with ``hint``) or unknown
    keys."""
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise InputError(f"{source}: {section} must be a mapping of settings{hint}, got {doc!r}")
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = set(doc) - known
    if unknown:
        raise InputError(f"{source}: unknown {section} settings {sorted(unknown)}; known: {sorted(known)}")
    return dict(doc)


def with_overrides(config: Any, items: Sequence[str], option: str) -> Any:
    """A copy of the dataclass ``config`` with ``FIELD=VALUE`` items applied (command-line overrides).

    Each value is parsed as its field's declared type (bool: true/false/1/0; int; float; str as given); an
    optional field (``X | None``) takes ``none`` or ``null`` as None, else an X. The dataclass's own checks then
    run. An unknown field, a malformed item or a bad value raises ``InputError`` naming ``option``.
    """
    fields = {f.name for f in dataclasses.fields(config)}
    hints = typing.get_type_hints(type(config))  # the declared types, postponed annotations resolved
    changes: dict[str, Any] = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or name not in fields:
            raise InputError(f"{option}: expected FIELD=VALUE with FIELD one of {sorted(fields)}, got {item!r}")
        declared = hints[name]
        args = typing.get_args(declared)
        optional = type(None) in args and len(args) == 2
        if optional and text.lower() in ("none", "null"):
            changes[name] = None
            continue
        kind = next(a for a in args if a is not type(None)) if optional else declared
        if kind not in (bool, int, float, str):
            raise InputError(f"{option}: field {name!r} ({declared}) cannot be set from the command line")
        try:
            if kind is bool:
                if text.lower() not in ("true", "false", "1", "0"):
                    raise ValueError(text)
                changes[name] = text.lower() in ("true", "1")
            else:
                changes[name] = kind(text)
        except ValueError:
            raise InputError(f"{option}: {name}={text!r} is not a {kind.__name__}") from None
    return dataclasses.replace(config, **changes)
