"""Settings by name for any tree of dataclasses: 'section.key=value' strings or Python values, typed as
the dataclass declares them and checked against the limits declared beside each field (`setting`).

Nothing here knows a particular config: `train/config.py` declares its fields with `setting`, and the
command line, saved runs and experiments all change them through `apply_overrides` (docs/design.md,
"Config overrides")."""

from __future__ import annotations

import copy
import dataclasses
import functools
import json
import math
import types
from collections.abc import Callable, Iterable, Mapping
from typing import Any, Literal, Union, get_args, get_origin, get_type_hints

_TRUE, _FALSE = ("true", "1", "yes", "on"), ("false", "0", "no", "off")


class OverrideError(ValueError):
    """A setting that names no field, or whose value does not fit the field's declared type or limits."""


def setting(
    default: Any = dataclasses.MISSING,
    *,
    factory: Callable[[], Any] | None = None,
    at_least: float | None = None,
    below: float | None = None,
    check: Callable[[Any], str | None] | None = None,
) -> Any:
    """A dataclass field with its limits beside it: a value under `at_least` or at or over `below` is
    refused, as is any value `check` describes as wrong (it returns what the value must be, or None).
    `None` is always let through (it means "as the data or another setting says")."""
    meta = {"at_least": at_least, "below": below, "check": check}
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def positive(value: float) -> str | None:
    """A `setting` check: what a value that must be above 0 must be."""
    return None if value > 0 else "a positive number"


def at_most_one(value: float) -> str | None:
    """A `setting` check for a fraction of a whole."""
    return None if value <= 1.0 else "at most 1 (a fraction)"


@functools.cache
def fields_of(cls: type) -> dict[str, tuple[Any, dataclasses.Field]]:
    """Every settable key of the dataclass `cls`, 'section.key' for a field of a nested dataclass or
    'key' at the top, with its declared type and its field."""
    out: dict[str, tuple[Any, dataclasses.Field]] = {}
    hints = get_type_hints(cls)
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        if dataclasses.is_dataclass(hint):
            section = get_type_hints(hint)
            out.update({f"{f.name}.{g.name}": (section[g.name], g) for g in dataclasses.fields(hint)})
        else:
            out[f.name] = (hint, f)
    return out


def describe(hint: Any) -> str:
    """The accepted values of a type, for error messages."""
    origin, args = get_origin(hint), get_args(hint)
    if origin in (Union, types.UnionType):
        return " or ".join("none" if a is type(None) else describe(a) for a in args)
    if origin is Literal:
        return "one of " + ", ".join(map(str, args))
    if origin in (list, tuple):
        return "a JSON array, " + str(hint).replace("typing.", "")
    names = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}
    return names.get(hint, str(hint))


def coerce(value: Any, hint: Any) -> Any:
    """`value` (a string to parse, or a Python value to check) as type `hint`, or a ValueError."""
    origin, args = get_origin(hint), get_args(hint)
    if origin in (Union, types.UnionType):
        if type(None) in args and (
            value is None or (isinstance(value, str) and value.lower() in ("none", "null"))
        ):
            return None
        for arg in (a for a in args if a is not type(None)):
            try:
                return coerce(value, arg)
            except ValueError:
                pass
        raise ValueError(value)
    if origin is Literal:
        for choice in args:
            if value == choice or (isinstance(value, str) and value == str(choice)):
                return choice
        raise ValueError(value)
    if origin in (list, tuple):
        if isinstance(value, str):
            value = json.loads(value)  # a JSONDecodeError is a ValueError
        if not isinstance(value, list | tuple):
            raise ValueError(value)
        if origin is list:
            return [coerce(v, args[0]) for v in value]
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(coerce(v, args[0]) for v in value)
        if len(value) != len(args):
            raise ValueError(value)
        return tuple(coerce(v, a) for v, a in zip(value, args, strict=True))
    if hint is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in _TRUE + _FALSE:
            return value.lower() in _TRUE
    elif hint in (int, float):
        if isinstance(value, str):
            return hint(value)
        if (
            isinstance(value, int | float)
            and not isinstance(value, bool)
            and (hint is float or isinstance(value, int))
        ):
            return hint(value)
    elif hint is str and isinstance(value, str):
        return value
    raise ValueError(value)


def _unknown(cls: type, key: str) -> OverrideError:
    keys = fields_of(cls)
    section, dot, _ = key.partition(".")
    sections = sorted({k.partition(".")[0] for k in keys if "." in k})
    if dot and section in sections:
        names = ", ".join(k.partition(".")[2] for k in keys if k.startswith(f"{section}."))
        return OverrideError(f"unknown setting {key!r}; {section} has {names}")
    if key in sections:
        return OverrideError(f"{key} is a section; set one of its keys, e.g. {key}.KEY=VALUE")
    top = ", ".join(k for k in keys if "." not in k)
    return OverrideError(
        f"unknown setting {key!r}; settings are SECTION.KEY for sections {', '.join(sections)}, or {top}"
    )


def _check_limits(key: str, value: Any, f: dataclasses.Field) -> None:
    """An OverrideError for a typed value no run can use (NaN, a zero batch, SH degree 7...)."""
    bad = None
    at_least, below, check = (f.metadata.get(k) for k in ("at_least", "below", "check"))
    if isinstance(value, float) and not math.isfinite(value):
        bad = "a finite number"
    elif value is None:
        return
    elif at_least is not None and value < at_least:
        bad = f"at least {at_least}"
    elif below is not None and value >= below:
        bad = f"less than {below:g}"
    elif check is not None:
        bad = check(value)
    if bad:
        raise OverrideError(f"{key} must be {bad}, got {value!r}")


def current_key(cls: type, key: str) -> str:
    """`key`, or what it is called now if `cls.RENAMED` (old -> new, optional) lists it."""
    return getattr(cls, "RENAMED", {}).get(key, key)


def typed(cls: type, key: str, value: Any) -> Any:
    """`value` typed for setting `key` of the dataclass `cls`, or an OverrideError naming the key and
    what it takes."""
    known = fields_of(cls)
    if current_key(cls, key) not in known:
        raise _unknown(cls, key)
    hint, f = known[current_key(cls, key)]
    try:
        out = coerce(value, hint)
    except ValueError:
        raise OverrideError(f"{key} takes {describe(hint)}, got {value!r}") from None
    _check_limits(key, out, f)
    return out


def parse_overrides(cls: type, items: Iterable[str]) -> dict[str, Any]:
    """'section.key=value' (or 'key=value') strings -> {key: typed value}, later items winning.

    Values are typed as the dataclass `cls` declares them; lists and tuples are written as JSON.
    """
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise OverrideError(f"{item!r}: expected KEY=VALUE, e.g. optim.lr_sh=1e-3")
        out[current_key(cls, key.strip())] = typed(cls, key.strip(), value.strip())
    return out


def apply_overrides(cfg: Any, overrides: Iterable[str] | Mapping[str, Any]) -> Any:
    """A copy of the dataclass `cfg` with settings changed by name, in order: 'key=value' strings (see
    `parse_overrides`), or a mapping of key -> value (a string is parsed, a Python value is checked)."""
    cls = type(cfg)
    if isinstance(overrides, Mapping):
        values = {current_key(cls, key): typed(cls, key, value) for key, value in overrides.items()}
    else:
        values = parse_overrides(cls, overrides)
    out = copy.deepcopy(cfg)
    for key, value in values.items():
        section, dot, name = key.partition(".")
        setattr(getattr(out, section) if dot else out, name if dot else section, value)
    return out


def flatten(d: Mapping[str, Any]) -> dict[str, Any]:
    """A nested dict's {'section.key': value} (one level of sections, as `fields_of` keys)."""
    flat: dict[str, Any] = {}
    for key, value in d.items():
        if isinstance(value, dict):
            flat.update({f"{key}.{k}": v for k, v in value.items()})
        else:
            flat[key] = value
    return flat
