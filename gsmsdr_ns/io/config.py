"""Dataclass configs from plain mappings (YAML / JSON documents), with errors that name the file and the key.

:func:`load_dataclass` overlays a mapping on a dataclass (its defaults, or a given base instance): unknown keys,
missing required keys and values of the wrong type are an :class:`~gsmsdr_ns.io.errors.InputError` naming the
source file and the dotted key (``motion.max_blur_px``, ``scenes[2].seed``). Nested dataclasses, lists / tuples
of them, ``Optional``, ``Literal`` and ``Path`` fields are understood; the dataclass's own ``__post_init__``
checks run as usual and their messages are prefixed with the source.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from pathlib import Path
from typing import Any, Mapping, Optional, Type, TypeVar, Union

from gsmsdr_ns.io.errors import InputError

T = TypeVar("T")


def read_yaml_mapping(path: Path) -> dict:
    """The top-level mapping of a YAML file (an empty file is ``{}``); :class:`InputError` naming the file."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    try:
        values = yaml.safe_load(path.read_text(encoding="utf8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        raise InputError(f"{path}: not valid YAML: {err}") from err
    values = {} if values is None else values
    if not isinstance(values, dict):
        raise InputError(f"{path}: must be a YAML mapping, got {type(values).__name__}")
    return values


def load_dataclass(
    cls: Type[T], values: Mapping[str, Any], source: Optional[Union[str, Path]] = None, base: Optional[T] = None
) -> T:
    """``cls`` built from ``values`` overlaid on ``base`` (default: ``cls``'s defaults); see the module docstring.

    ``source`` (a file name) prefixes every message. A nested dataclass field takes a mapping that is overlaid on
    the base's value of that field (``None`` keeps it).
    """
    prefix = f"{source}: " if source is not None else ""
    return _load(cls, values, prefix, "", base)


def _load(cls: type, values: Any, prefix: str, key: str, base: Any) -> Any:
    section = key or cls.__name__
    if not isinstance(values, Mapping):
        raise InputError(f"{prefix}{section}: must be a mapping of {cls.__name__} fields, got {type(values).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(str(k) for k in values if k not in fields)
    if unknown:
        raise InputError(f"{prefix}unknown {section} keys: {unknown}; valid keys: {sorted(fields)}")
    if base is None:
        missing = [
            name for name, f in fields.items()
            if name not in values and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        ]  # fmt: skip
        if missing:
            raise InputError(f"{prefix}{section}: missing required keys {missing}")
    hints = typing.get_type_hints(cls)
    checked = {}
    for name, value in values.items():
        sub_key = f"{key}.{name}" if key else name
        sub_base = getattr(base, name) if base is not None else None
        checked[name] = _convert(hints.get(name, Any), value, prefix, sub_key, sub_base)
    try:
        return dataclasses.replace(base, **checked) if base is not None else cls(**checked)
    except (TypeError, ValueError) as err:
        where = f"{key}: " if key else ""
        raise InputError(f"{prefix}{where}{err}") from err


def _fail(prefix: str, key: str, expected: str, value: Any) -> InputError:
    return InputError(f"{prefix}{key}: must be {expected}, got {value!r}")


def _convert(tp: Any, value: Any, prefix: str, key: str, base: Any = None) -> Any:
    """``value`` checked against the annotation ``tp`` (and converted: list -> tuple, str -> Path, int -> float)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is Any or tp is object:
        return value
    if dataclasses.is_dataclass(tp):
        if value is None and base is not None:
            return base
        return _load(tp, {} if value is None else value, prefix, key, base)
    if origin is Union or (hasattr(types, "UnionType") and isinstance(tp, types.UnionType)):
        if value is None and type(None) in args:
            return None
        options = [a for a in args if a is not type(None)]
        errors = []
        for option in options:
            try:
                return _convert(option, value, prefix, key, base)
            except InputError as err:
                errors.append(err)
        if len(errors) == 1:
            raise errors[0]
        raise _fail(prefix, key, " or ".join(_describe(a) for a in args), value)
    if origin is typing.Literal:
        if not any(value == a and type(value) is type(a) for a in args):
            raise _fail(prefix, key, f"one of {list(args)}", value)
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise _fail(prefix, key, f"a list ({_describe(tp)})", value)
        if origin is tuple and args and not (len(args) == 2 and args[1] is Ellipsis):
            if len(value) != len(args):
                raise _fail(prefix, key, f"a list of {len(args)} items ({_describe(tp)})", value)
            items = [_convert(a, v, prefix, f"{key}[{i}]") for i, (a, v) in enumerate(zip(args, value))]
        else:
            item = args[0] if args else Any
            items = [_convert(item, v, prefix, f"{key}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin in (dict, Mapping, typing.Mapping) or tp in (dict, Mapping):
        if not isinstance(value, Mapping):
            raise _fail(prefix, key, "a mapping", value)
        return dict(value)
    if tp is bool:
        if not isinstance(value, bool):
            raise _fail(prefix, key, "true or false", value)
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise _fail(prefix, key, "an integer", value)
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _fail(prefix, key, "a number", value)
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise _fail(prefix, key, "a string", value)
        return value
    if tp is Path:
        if not isinstance(value, (str, Path)):
            raise _fail(prefix, key, "a path", value)
        return Path(value)
    return value  # other annotations are not checked here; the dataclass's own checks still run


def _describe(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")
