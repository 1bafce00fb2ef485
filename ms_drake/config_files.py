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


@functools.cache
def _settable(schema):
    """The schema itself, or for a frozen dataclass a subclass whose fields Drake's YAML may set."""
    if not schema.__dataclass_params__.frozen:
        return schema
    return type(schema.__name__, (schema,), {"__setattr__": object.__setattr__, "__delattr__": object.__delattr__})


def _typed_load(schema, base, **where):
    """yaml_load_typed of `where` (filename= or data=) over `base`, as a `schema`."""
    work = _settable(schema)
    loaded = yaml_load_typed(schema=work, defaults=work(**dataclasses.asdict(base)) if work is not schema else base,
                             **where)
    return loaded if work is schema else schema(**dataclasses.asdict(loaded))


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
