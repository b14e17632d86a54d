"""Reading config YAML and turning validation failures into one line: `FILE: field 'a.b': expected ...`.

An unknown section or key names the file, the key and the valid ones; invalid YAML names file:line. Presets are
YAML files in the package's `configs/` folder (`swarmsplat.configs`), found by name.
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path
from typing import Any, get_args

import yaml
from pydantic import BaseModel, ValidationError

from swarmsplat.kernels.errors import InputError


def read_yaml(path: str | Path) -> dict[str, Any]:
    """The mapping in YAML file `path` ({} for an empty file); InputError naming file (and line) otherwise."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"config file not found: {path}")
    try:
        loaded = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        raise InputError(f"{where}: invalid YAML ({getattr(e, 'problem', None) or e})") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: cannot read the config file ({e})") from None
    if loaded is None:
        return {}
    if not isinstance(loaded, dict):
        raise InputError(f"{path}: expected a mapping of config sections at the top level, got "
                         f"{type(loaded).__name__}")
    return loaded


def deep_merge(base: dict, upd: dict) -> dict:
    """`base` with `upd` merged in, section by section (a new dict; neither argument changes)."""
    out = dict(base)
    for k, v in upd.items():
        out[k] = deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def validate(model: type[BaseModel], data: dict, where: str) -> BaseModel:
    """model.model_validate(data); a failure becomes InputError(`where: field 'a.b': expected ...`)."""
    try:
        return model.model_validate(data)
    except ValidationError as e:
        raise InputError(f"{where}: {explain(model, e.errors()[0])}") from None


def _submodel(model: type[BaseModel], loc: tuple) -> type[BaseModel] | None:
    """The model class at field path `loc` below `model` (None when the path leaves the models)."""
    for part in loc:
        info = model.model_fields.get(part) if isinstance(part, str) else None
        if info is None:
            return None
        ann = info.annotation
        cands = [ann, *get_args(ann)]
        model = next((c for c in cands if isinstance(c, type) and issubclass(c, BaseModel)), None)
        if model is None:
            return None
    return model


def _field_path(model: type[BaseModel], loc: tuple) -> tuple:
    """`loc` without pydantic's union-member tags (e.g. 'str', 'float'), which are not keys the user wrote."""
    out, m = [], model
    for part in loc:
        if m is not None and isinstance(part, str) and part not in m.model_fields:
            continue
        out.append(part)
        m = _submodel(m, (part,)) if m is not None else None
    return tuple(out)


def _got(value: Any) -> str:
    return f"got {value!r}" if not isinstance(value, dict) else "got a mapping"


def explain(model: type[BaseModel], err: dict) -> str:
    """One pydantic error as `field 'a.b': expected ..., got ...` (unknown keys list the valid ones)."""
    loc = tuple(err["loc"])
    kind, ctx, value = err["type"], err.get("ctx") or {}, err.get("input")
    if kind == "extra_forbidden":
        parent = _submodel(model, loc[:-1])
        valid = ", ".join(parent.model_fields) if parent is not None else "?"
        what = "section or key" if len(loc) == 1 else f"key of section '{'.'.join(map(str, loc[:-1]))}'"
        return f"field '{'.'.join(map(str, loc))}': unknown {what}; expected one of {valid}"
    loc = _field_path(model, loc)
    field = ".".join(str(p) for p in loc) or "(top level)"
    bounds = {"greater_than_equal": (">=", "ge"), "greater_than": (">", "gt"), "less_than_equal": ("<=", "le"),
              "less_than": ("<", "lt")}
    types = {"int": "an integer", "float": "a number", "bool": "true or false", "string": "a string"}
    if kind in bounds:
        op, key = bounds[kind]
        bound = ctx.get(key)
        expected = f"a number {op} {bound:g}" if isinstance(bound, float) else f"a number {op} {bound}"
    elif kind == "literal_error":
        expected = f"one of {ctx.get('expected')}"
    elif kind.split("_")[0] in types and kind.endswith(("_type", "_parsing", "_from_float", "_fraction")):
        expected = types[kind.split("_")[0]]
    elif kind in ("model_type", "model_attributes_type", "dict_type"):
        expected = "a mapping of keys"
    elif kind == "value_error":
        return f"field '{field}': {str(err['msg']).removeprefix('Value error, ')}"
    else:
        expected = str(err["msg"])
        expected = expected[:1].lower() + expected[1:]
    return f"field '{field}': expected {expected}, {_got(value)}"


def presets_folder():
    """The folder of preset YAML files (`configs/` in the repository, `swarmsplat/configs/` installed)."""
    return importlib.resources.files("swarmsplat.configs")


def preset_names() -> list[str]:
    """The presets that exist: the names of configs/*.yaml without the suffix, sorted."""
    return sorted(p.name[: -len(".yaml")] for p in presets_folder().iterdir() if p.name.endswith(".yaml"))


def preset_path(name: str) -> Path:
    """The file of preset `name`; InputError listing the presets for an unknown name."""
    names = preset_names()
    if name not in names:
        raise InputError(f"unknown preset {name!r}; choose one of {', '.join(names)}")
    return Path(str(presets_folder() / f"{name}.yaml"))
