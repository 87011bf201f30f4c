"""Typed, frozen dataclass configs: conversion, validation and CLI flag generation.

Every step of the pipeline takes one frozen dataclass config. That dataclass is the
single source of defaults: the CLI flags are generated from it
(:func:`add_config_arguments`), dictionaries are checked against it
(:func:`config_from_dict`, unknown keys are errors) and the resolved config is saved
next to the outputs (the bytes of :func:`config_json_bytes`, written atomically by the step) and inside
every checkpoint. This module imports nothing of the package but its errors.

Supported field types: ``bool``, ``int``, ``float``, ``str``, ``pathlib.Path``,
``Literal[...]``, ``X | None`` of those, ``tuple[T, ...]`` of scalars and nested
config dataclasses. A nested config whose field carries ``metadata={"flag_prefix": P}`` is exposed
as flags: each of its fields ``F`` becomes ``--{P}{F}`` (or the absolute ``metadata["flag"]`` of
that field), grouped under the nested field's ``metadata["title"]``; other nested configs are set
through ``--config_file`` only. Mappings may use those flag names as keys as well as the nested
form (:func:`config_from_dict`); a class may list options it no longer has in a ``REMOVED_OPTIONS``
class attribute (flag name -> the value now fixed), which are then accepted with a warning when they
hold that value. Such an entry is kept only for a user's saved file, and its comment names the
version that drops it (``tests/test_structure.py``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import numbers
import os
import types
import typing
from pathlib import Path
from typing import Any, Literal, TypeVar, Union, get_args, get_origin, get_type_hints

from .errors import ConfigError

C = TypeVar("C")
logger = logging.getLogger(__name__)

_TRUE = {"1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}


def parse_bool(text: str | bool) -> bool:
    """Parse COLMAP-style booleans (``1/0``, ``true/false``, ``yes/no``)."""
    if isinstance(text, bool):
        return text
    low = str(text).strip().lower()
    if low in _TRUE:
        return True
    if low in _FALSE:
        return False
    raise ConfigError(f"expected a boolean (true/false/1/0), got {text!r}")


def check_range(
    name: str, value: float, *, low: float | None = None, high: float | None = None
) -> None:
    """Raise :class:`ConfigError` naming ``name`` unless ``low <= value <= high`` (and finite)."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (low is None or value >= low) and (high is None or value <= high)
    if not ok:
        bounds = " and ".join(
            b for b in (f">= {low}" if low is not None else "", f"<= {high}" if high is not None else "") if b
        )
        raise ConfigError(f"{name} must be a finite number{' ' + bounds if bounds else ''}, got {value!r}")


#: A thread count above ``THREADS_PER_CPU`` x this machine's CPUs (and above ``MIN_THREAD_CAP``) is refused:
#: so many threads fail to start (a crash in OpenMP, Open3D or COLMAP) or only slow the run down.
THREADS_PER_CPU = 4
MIN_THREAD_CAP = 256


def check_threads(name: str, value: int, *, auto: int | None) -> None:
    """Raise :class:`ConfigError` naming ``name`` unless ``value`` is ``auto`` (the option's "all cores" or
    "default" value; ``None``: none) or ``1 .. max(MIN_THREAD_CAP, THREADS_PER_CPU x os.cpu_count())``."""
    cpus = os.cpu_count() or 1
    cap = max(MIN_THREAD_CAP, THREADS_PER_CPU * cpus)
    ok = isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if ok and (value == auto or 1 <= value <= cap):
        return
    meaning = {0: "the default", -1: "all cores"}.get(auto, "")
    allowed = (f"{auto} ({meaning}) or " if auto is not None else "") + f"1 to {cap}"
    raise ConfigError(f"{name} must be {allowed} (the larger of {MIN_THREAD_CAP} and {THREADS_PER_CPU} x "
                      f"this machine's {cpus} CPUs), got {value!r}")


def check_int_fields(cfg: Any, prefix: str = "") -> None:
    """Raise :class:`ConfigError` naming the field unless every field of the dataclass ``cfg``
    annotated ``int`` holds an integer (not a bool). A ``float`` passed in Python code is refused;
    flags and config files go through :func:`config_from_dict`, which turns a whole-number value
    (``"30"``, ``30.0``) into an ``int`` and refuses others. ``prefix``: the flag prefix of a nested
    config, so that the message names the flag."""
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if f.type in (int, "int") and (isinstance(value, bool) or not isinstance(value, numbers.Integral)):
            raise ConfigError(f"{prefix}{f.name} must be an integer, got {value!r}")


def _unwrap_optional(tp: Any) -> tuple[Any, bool]:
    origin = get_origin(tp)
    if origin in (Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(get_args(tp)) == 2:
            return args[0], True
    return tp, False


def _coerce(value: Any, tp: Any, where: str) -> Any:
    """Convert ``value`` (from JSON or the CLI) to the annotated type ``tp``."""
    inner, optional = _unwrap_optional(tp)
    if value is None:
        if optional:
            return None
        raise ConfigError(f"{where}: None is not allowed (type {tp})")
    tp = inner
    origin = get_origin(tp)
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping for {tp.__name__}, got {value!r}")
        return config_from_dict(tp, value, _where=where)
    if origin is Literal:
        choices = get_args(tp)
        if value not in choices:
            raise ConfigError(f"{where}: {value!r} is not one of {list(choices)}")
        return value
    if origin is tuple:
        args = get_args(tp)
        if isinstance(value, str):
            value = [v for v in value.replace(",", " ").split() if v]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{where}[{i}]") for i, v in enumerate(value))
        if len(args) != len(value):
            raise ConfigError(f"{where}: expected {len(args)} values, got {value!r}")
        return tuple(_coerce(v, a, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value, strict=True)))
    if tp is bool:
        try:
            return parse_bool(value)
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from None
    if tp is int:
        if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        try:
            return int(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{where}: expected an integer, got {value!r}") from None
    if tp is float:
        if isinstance(value, bool):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{where}: expected a number, got {value!r}") from None
        if math.isnan(number):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return number
    if tp is str:
        if not isinstance(value, (str, Path)):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return str(value)
    if tp is Path:
        if not isinstance(value, (str, Path)):
            raise ConfigError(f"{where}: expected a path, got {value!r}")
        return Path(value)
    raise ConfigError(f"{where}: unsupported config field type {tp!r}")


def _hints(cls: type) -> dict[str, Any]:
    return get_type_hints(cls)


def _field_default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


@dataclasses.dataclass(frozen=True)
class FlagSpec:
    """One command-line flag of a config: the ``path`` of field names to it (nested configs first),
    its dataclass ``field`` and annotated ``type``, the argparse ``group`` title ("" at the top) and
    its ``default`` (from the enclosing config's default instance where there is one)."""

    path: tuple[str, ...]
    field: dataclasses.Field
    type: Any
    group: str
    default: Any


def config_flags(cls: type, default: Any = None) -> dict[str, FlagSpec]:
    """Flag name -> :class:`FlagSpec` of every field of ``cls`` that is a flag (module docstring)."""
    hints = _hints(cls)
    out: dict[str, FlagSpec] = {}
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        tp, _ = _unwrap_optional(hints[f.name])
        value = getattr(default, f.name) if default is not None else _field_default(f)
        if not dataclasses.is_dataclass(tp):
            out[f.metadata.get("flag", f.name)] = FlagSpec((f.name,), f, hints[f.name], "", value)
            continue
        if "flag_prefix" not in f.metadata:
            continue
        skip = set(f.metadata.get("exclude_flags", ()))
        for flag, spec in config_flags(tp, value).items():
            if spec.path[0] in skip:
                continue
            name = flag if "flag" in spec.field.metadata else f.metadata["flag_prefix"] + flag
            if name in out:
                raise TypeError(f"{cls.__name__}: two fields have the flag --{name}")
            out[name] = FlagSpec((f.name, *spec.path), spec.field, spec.type,
                                 spec.group or f.metadata.get("title", f.name), spec.default)
    return out


def removed_options(cls: type) -> dict[str, Any]:
    """Flag name -> fixed value of every option ``cls`` no longer has: its ``REMOVED_OPTIONS`` and
    those of its nested configs that are flags (module docstring)."""
    out = dict(getattr(cls, "REMOVED_OPTIONS", {}))
    hints = _hints(cls)
    for f in dataclasses.fields(cls):
        tp, _ = _unwrap_optional(hints[f.name])
        if f.init and dataclasses.is_dataclass(tp) and "flag_prefix" in f.metadata:
            out.update({f.metadata["flag_prefix"] + k: v for k, v in removed_options(tp).items()})
    return out


def _set_path(data: dict, path: tuple[str, ...], value: Any) -> None:
    for key in path[:-1]:
        inner = data.get(key)
        if dataclasses.is_dataclass(inner):
            inner = config_to_dict(inner)
        if not isinstance(inner, dict):
            inner = {}
        data[key] = inner
        data = inner
    data[path[-1]] = value


def merge_configs(base: dict, update: dict) -> dict:
    """``base`` with ``update``'s values, nested mappings merged key by key."""
    out = dict(base)
    for k, v in update.items():
        out[k] = merge_configs(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _suggest(word: str, choices: typing.Iterable[str]) -> str:
    import difflib

    near = difflib.get_close_matches(word.replace("-", "_"), list(choices), n=1, cutoff=0.6)
    return f"; did you mean {near[0]!r}?" if near else ""


def flags_to_dict(cls: type, flags: dict[str, Any], *, where: str | None = None) -> dict[str, Any]:
    """The nested mapping of ``cls`` that the flag values ``flags`` (flag name -> value) set.

    Keys that are field names of ``cls`` (nested configs as mappings or instances) pass through;
    a key in :func:`removed_options` is dropped with a warning when it holds the value that option
    now has, else refused.
    """
    where = where or cls.__name__
    specs = config_flags(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    removed = removed_options(cls)
    data: dict[str, Any] = {}
    for key, value in flags.items():
        if key in specs:
            _set_path(data, specs[key].path, value)
        elif key in names:
            value = config_to_dict(value) if dataclasses.is_dataclass(value) else value
            data[key] = merge_configs(data[key], value) if isinstance(value, dict) and isinstance(
                data.get(key), dict) else value
        elif key in removed:
            fixed = removed[key]
            try:
                same = _coerce(value, type(fixed), f"{where}.{key}") == fixed
            except ConfigError:
                same = False
            if not same:
                raise ConfigError(f"{where}: option {key!r} was removed; it is now always {fixed!r} "
                                  f"(got {value!r}): drop it")
            logger.warning("%s: option %r was removed (it is always %r); ignoring it", where, key, fixed)
        else:
            raise ConfigError(f"{where}: unknown config key {key!r}{_suggest(key, [*specs, *names])}")
    return data


def config_from_dict(cls: type[C], data: dict[str, Any], *, _where: str | None = None) -> C:
    """Build ``cls`` from a mapping. Unknown keys and ill-typed values raise :class:`ConfigError`.

    Keys are field names (nested configs as mappings, merged into their defaults) or flag names
    (:func:`config_flags`).
    """
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    where = _where or cls.__name__
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    data = flags_to_dict(cls, data, where=where)
    hints = _hints(cls)
    kwargs = {}
    for k, v in data.items():
        tp, _ = _unwrap_optional(hints[k])
        if dataclasses.is_dataclass(tp) and isinstance(v, dict):
            default = _field_default(fields[k])  # a partial mapping overrides the field's default
            if default is not None:
                v = merge_configs(config_to_dict(default), v)
        kwargs[k] = _coerce(v, hints[k], f"{where}.{k}")
    return cls(**kwargs)


def replace_config(cfg: C, **changes: Any) -> C:
    """Like :func:`dataclasses.replace`, but type-checked and strict about unknown keys; ``changes``
    may name fields or flags (``replace_config(stereo_cfg, geom_fill=False)``)."""
    changed = flags_to_dict(type(cfg), changes)
    return config_from_dict(type(cfg), merge_configs(config_to_dict(cfg), changed))


def _jsonable(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return config_to_dict(value)
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, tuple):
        return [_jsonable(v) for v in value]
    return value


def config_to_dict(cfg: Any) -> dict[str, Any]:
    """Plain JSON-compatible dict of a config (nested configs become dicts)."""
    if not dataclasses.is_dataclass(cfg) or isinstance(cfg, type):
        raise TypeError(f"{cfg!r} is not a dataclass instance")
    return {f.name: _jsonable(getattr(cfg, f.name)) for f in dataclasses.fields(cfg) if f.init}


def config_to_flags(cfg: Any) -> dict[str, Any]:
    """Flag name -> JSON-compatible value of every flag of ``cfg`` (:func:`config_flags`)."""
    out = {}
    for flag, spec in config_flags(type(cfg)).items():
        value = cfg
        for name in spec.path:
            value = getattr(value, name)
        out[flag] = _jsonable(value)
    return out


def config_json_bytes(cfg: Any, **extra: Any) -> bytes:
    """The resolved config as the bytes of a JSON file (``extra`` keys stored beside it), for the step
    to write next to its outputs with :func:`colmap_pvs.io.files.atomic_write_bytes`; read back by
    :func:`load_config`."""
    payload = {"config_class": type(cfg).__name__, "config": config_to_dict(cfg)}
    payload.update({k: _jsonable(v) for k, v in extra.items()})
    return (json.dumps(payload, indent=2, sort_keys=True) + "\n").encode()


def load_config(cls: type[C], path: str | os.PathLike) -> C:
    """Load a config written as :func:`config_json_bytes` (or a plain JSON mapping; see
    :func:`read_config_file`)."""
    return config_from_dict(cls, read_config_file(cls, path))


def read_config_file(cls: type, path: str | os.PathLike, *, where: str | None = None) -> dict[str, Any]:
    """The nested values of ``cls`` a JSON config file sets: a mapping (field or flag names, nested
    or not), or a file of :func:`config_json_bytes` whose optional ``"base"`` names, relative to it, a config
    file it changes (read first, this file's values merged over it), so a recorded variant holds only
    what differs. ``where`` names the file in errors (default: ``config file 'PATH'``)."""
    return _read_config_file(cls, Path(path), where, ())


def _read_config_file(cls: type, path: Path, where: str | None, chain: tuple[Path, ...]) -> dict[str, Any]:
    where = where or f"config file {str(path)!r}"
    if path.resolve() in chain:
        raise ConfigError(f"{where}: its \"base\" chain comes back to it")
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))
    except FileNotFoundError:
        raise ConfigError(f"{where} does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"cannot read {where}: {exc}") from None
    base = None
    if isinstance(data, dict) and "config" in data and "config_class" in data:
        base = data.get("base")
        data = data["config"]
    if not isinstance(data, dict):
        raise ConfigError(f"{where} must hold a JSON object")
    data = flags_to_dict(cls, data, where=where)
    if base is None:
        return data
    if not isinstance(base, str):
        raise ConfigError(f"{where}: \"base\" must be a file name, got {base!r}")
    base_path = path.parent / base
    chain = (*chain, path.resolve())
    inherited = _read_config_file(cls, base_path, f"{where}'s base {str(base_path)!r}", chain)
    return merge_configs(inherited, data)


# --------------------------------------------------------------------------- CLI flags


def _bool_flag(text: str) -> bool:
    try:
        return parse_bool(text)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _field_help(field: dataclasses.Field) -> str:
    return str(field.metadata.get("help", ""))


def add_config_arguments(
    parser: argparse.ArgumentParser,
    cls: type,
    *,
    exclude: typing.Iterable[str] = (),
    required: typing.Iterable[str] = (),
) -> None:
    """Add one ``--flag`` per flag of ``cls`` (:func:`config_flags`, COLMAP style), in one argparse
    group per nested config.

    Defaults are not duplicated: a flag that is not given stays absent from the
    parsed namespace (``argparse.SUPPRESS``) and the dataclass default applies.
    Help texts come from ``field(metadata={"help": ...})``.
    """
    exclude = set(exclude)
    required = set(required)
    groups: dict[str, Any] = {}
    for flag, spec in config_flags(cls).items():
        if flag in exclude:
            continue
        tp, _optional = _unwrap_optional(spec.type)
        origin = get_origin(tp)
        help_text = _field_help(spec.field)
        long_choices = origin is Literal and len(",".join(map(str, get_args(tp)))) > 20
        if long_choices:  # listed in the help, so that every flag keeps its help on its own line
            help_text = f"{help_text}: {', '.join(map(str, get_args(tp)))}"
        if flag not in required and "default:" not in help_text:
            shown = _jsonable(spec.default)
            help_text = f"{help_text} (default: {shown if shown != '' else repr(shown)})".strip()
        help_text = help_text.replace("%", "%%")  # argparse %-formats help texts
        kwargs: dict[str, Any] = {"dest": flag, "help": help_text, "default": argparse.SUPPRESS}
        if origin is Literal:
            kwargs["choices"] = list(get_args(tp))
            kwargs["metavar"] = "MODE" if long_choices else "{" + ",".join(map(str, get_args(tp))) + "}"
        elif origin is tuple:
            kwargs["nargs"] = "+"
            kwargs["metavar"] = "V"
        elif tp is bool:  # bare `--flag` is true; `--flag false` / `--flag=0` work too
            kwargs["type"] = _bool_flag
            kwargs["metavar"] = "BOOL"
            kwargs["nargs"] = "?"
            kwargs["const"] = True
        elif tp in (int, float, str, Path):
            kwargs["type"] = str if tp is Path else tp
            kwargs["metavar"] = {int: "N", float: "X", str: "TEXT", Path: "PATH"}[tp]
        else:
            continue
        if flag in required:
            kwargs["required"] = True
        if spec.group not in groups:
            groups[spec.group] = parser.add_argument_group(spec.group) if spec.group else parser
        groups[spec.group].add_argument(f"--{flag}", **kwargs)
    for flag in removed_options(cls):  # accepted (with a warning when it holds its fixed value), not listed
        parser.add_argument(f"--{flag}", dest=flag, default=argparse.SUPPRESS, help=argparse.SUPPRESS)


def config_from_args(cls: type[C], args: argparse.Namespace, **overrides: Any) -> C:
    """Build ``cls`` from the flags that were given on the command line (plus ``overrides``)."""
    names = set(config_flags(cls)) | set(removed_options(cls))
    data = {k: v for k, v in vars(args).items() if k in names}
    data.update(overrides)
    return config_from_dict(cls, data)
