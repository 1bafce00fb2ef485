"""Task configs as Drake YAML: one dataclass per task kind (bin search, shelf search, push study,
rearrangement), read from a file or a named setting, then overridden field by field.

`load_config(schema, path, overrides, named, **fields)`: the schema's defaults, then the YAML file
`path` (any subset of the fields; or the name of a setting in `named`), then `fields`, then each
override "dotted.key=value" (a YAML value, e.g. "ablation.grasp_outcome=draw", "heap.objects=15").
Every bad file, key or value is one `ConfigError` naming it and the fix. A schema's nested parts
are dataclasses too; its `__post_init__` validates the values (and turns nested dicts back into
their dataclasses, so `Schema(**dataclasses.asdict(config))` reads a record's config back).
"""

import dataclasses
import functools
import typing
from pathlib import Path

from pydrake.common.yaml import yaml_dump, yaml_load_typed

from ms_drake.errors import MsDrakeError


class ConfigError(MsDrakeError, ValueError):
    """A config file, key or value that cannot be used (names it and the fix)."""


_YAML_ERRORS = (RuntimeError, ValueError, TypeError, AssertionError)


@functools.cache
def _resolve_annotations(schema) -> None:
    """Drake's YAML reads a dataclass's field types: resolve the string annotations of a module with
    `from __future__ import annotations` to the types themselves (nested dataclasses too)."""
    hints = typing.get_type_hints(schema)
    for f in dataclasses.fields(schema):
        f.type = hints[f.name]
        for arg in (f.type, *typing.get_args(f.type)):
            if dataclasses.is_dataclass(arg):
                _resolve_annotations(arg)


def _dataclass_arg(tp):
    """The dataclass a field's type names (itself, or inside Optional / a union), else None."""
    for arg in (tp, *typing.get_args(tp)):
        if dataclasses.is_dataclass(arg):
            return arg
    return None


def _frozen_inside(schema) -> bool:
    return schema.__dataclass_params__.frozen or any(
        _frozen_inside(_dataclass_arg(f.type)) for f in dataclasses.fields(schema) if _dataclass_arg(f.type))


@functools.cache
def _settable(schema):
    """The schema itself, or, when it or one of its parts is a frozen dataclass, a plain dataclass of
    the same fields (parts likewise) that Drake's YAML may set."""
    if not _frozen_inside(schema):
        return schema
    fields = []
    for f in dataclasses.fields(schema):
        part = _dataclass_arg(f.type)
        tp = f.type if part is None else (_settable(part) if part is f.type else typing.Optional[_settable(part)])
        default = ({"default": f.default} if f.default is not dataclasses.MISSING else
                   {"default_factory": f.default_factory} if f.default_factory is not dataclasses.MISSING else {})
        if part is not None and "default_factory" in default:
            default = {"default_factory": _settable(part)}
        fields.append((f.name, tp, dataclasses.field(**default)))
    return dataclasses.make_dataclass(schema.__name__, fields)


def _as(schema, value):
    """`value` (a dataclass of the same fields, or their dict) as an instance of `schema`, parts too."""
    d = value if isinstance(value, dict) else dataclasses.asdict(value)
    kwargs = {}
    for f in dataclasses.fields(schema):
        v, part = d[f.name], _dataclass_arg(f.type)
        kwargs[f.name] = _as(part, v) if part is not None and isinstance(v, dict) else v
    return schema(**kwargs)


def _typed_load(schema, base, **where):
    """yaml_load_typed of `where` (filename= or data=) over `base`, as a `schema`."""
    work = _settable(schema)
    if work is schema:
        return yaml_load_typed(schema=schema, defaults=base, **where)
    loaded = yaml_load_typed(schema=work, defaults=_as(work, base), **where)
    return schema(**dataclasses.asdict(loaded))


def _rebuild(schema, config):
    """The config re-made through the schema's constructor (its checks run)."""
    return schema(**dataclasses.asdict(config))


def load_config(schema, path=None, overrides=(), named: dict | None = None, **fields):
    named = named or {}
    name = schema.__name__
    _resolve_annotations(schema)
    try:
        if path is None:
            base = schema(**fields)
        else:
            if str(path) in named:
                path = named[str(path)]
            elif not Path(path).is_file():
                raise ConfigError(f"config {str(path)!r}: no such file" + (" or named setting" if named else "")
                                  + f"; give a YAML file of {name}'s fields"
                                  + (f" or one of {', '.join(named)}" if named else ""))
            try:
                base = _typed_load(schema, schema(), filename=str(path))
            except _YAML_ERRORS as e:
                raise ConfigError(f"{path}: {str(e).splitlines()[0]}") from None
            base = schema(**{**dataclasses.asdict(base), **fields})
        for item in overrides:
            key, sep, value = str(item).partition("=")
            if not sep or not key.strip():
                raise ConfigError(f"--set {item!r}: write KEY=VALUE, e.g. {dataclasses.fields(schema)[0].name}=...")
            tree = leaf_parent = {}
            *parents, leaf = key.strip().split(".")
            for p in parents:
                leaf_parent[p] = {}
                leaf_parent = leaf_parent[p]
            leaf_parent[leaf] = "__VALUE__"
            text = yaml_dump(tree).replace("__VALUE__", value.strip() or "''")
            try:
                base = _typed_load(schema, base, data=text)
            except _YAML_ERRORS as e:
                raise ConfigError(f"--set {item!r}: {str(e).splitlines()[0]}; the keys are the fields of {name} "
                                  f"({', '.join(f.name for f in dataclasses.fields(schema))}) and of its parts") \
                    from None
        if overrides:  # checked once all are applied: one may need another (a planner and its outcome)
            base = _rebuild(schema, base)
    except ConfigError:
        raise
    except MsDrakeError as e:  # the schema's own checks
        raise ConfigError(str(e)) from None
    return base


def config_dict(config, drop=("seed",)) -> dict:
    """The config as plain data for a record, without the per-run fields `drop`."""
    d = dataclasses.asdict(config)
    for k in drop:
        d.pop(k, None)
    return d
