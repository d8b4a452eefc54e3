"""Configuration: TOML files, `--set key=value` overrides, canonical JSON, and the
check of a whole config against the sections of `ptovs.registry`.

A config file has one table per stage (`[uncertainty]`, `[train-ae]`, ...) plus
`[scene]` for how scenes are read. `--set` takes `section.key=value` on the group
and `key=value` (or `section.key=value`) on a stage command. Values are parsed as
TOML (`--set tau_u=0.85`, `--set levels=[1,2]`, `--set name=abc` falls back to a
string).
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import types
import typing
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from ptovs.errors import InputError, MissingInputError
from ptovs.registry import config_class, config_keys, config_sections, section_names

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - python 3.10
    import tomli as tomllib


def load_config(path: str | Path | None) -> dict[str, Any]:
    """Read a TOML config file into nested dicts; `None` gives an empty config."""
    if path is None:
        return {}
    path = Path(path)
    if not path.is_file():
        raise MissingInputError(
            f"config file {path} does not exist; pass an existing TOML file to "
            "--config (see configs/default.toml)"
        )
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"config file {path} is not valid TOML: {exc}") from None


def parse_value(text: str) -> Any:
    """Parse one `--set` value as TOML, falling back to the raw string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        t = text.strip()
        if t.startswith("[") and t.endswith("]"):  # [s,m]: the shell ate the quotes
            return [parse_value(w.strip()) for w in t[1:-1].split(",") if w.strip()]
        return text


def parse_sets(items: Iterable[str], section: str | None = None) -> dict[str, Any]:
    """Turn `["a.b=1", "c=x"]` into nested dicts.

    Args:
        items: `key=value` strings; keys may be dotted (`train-ae.lr=1e-3`).
        section: section that undotted keys belong to; `None` requires dotted keys.

    Returns:
        `{section: {key: value}}` ready for `merge`.
    """
    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise InputError(
                f"--set {item!r}: expected key=value, e.g. --set tau_u=0.85"
            )
        key, value = item.split("=", 1)
        key = key.strip()
        parts = key.split(".")
        if len(parts) == 1:
            if section is None:
                raise InputError(
                    f"--set {item!r}: on the ptovs group a key needs its section: "
                    + _sections_with(key, value.strip())
                )
            parts = [section, key]
        if any(not p for p in parts):
            raise InputError(f"--set {item!r}: empty key part")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = parse_value(value.strip())
    return out


def did_you_mean(name: str, choices: Iterable[str], fmt: str = "{!r}") -> str:
    """ " (did you mean X?)" for the nearest of `choices`, or ""."""
    import difflib

    near = difflib.get_close_matches(name, list(choices), n=1)
    return f" (did you mean {fmt.format(near[0])}?)" if near else ""


def _sections_with(key: str, value: str) -> str:
    """Advice for a key given without its section: the sections that have it."""
    sections = config_sections()
    have = [name for name, keys in sections.items() if key in keys]
    if not have:
        import difflib

        every = [f"{n}.{k}" for n, keys in sections.items() for k in keys]
        near = difflib.get_close_matches(key, [e.split(".", 1)[1] for e in every], 3)
        hint = [e for e in every if e.split(".", 1)[1] in near][:3]
        return f"no section has a key {key!r}" + (
            f" (did you mean {' or '.join(hint)}?)" if hint else
            "; `ptovs <command> --help` lists each stage's keys"
        )  # fmt: skip
    return " or ".join(f"--set {name}.{key}={value}" for name in have)


def merge(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """Recursive dict merge; `override` wins."""
    out = dict(base)
    for k, v in override.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = merge(out[k], v)
        else:
            out[k] = v
    return out


def _jsonable(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {
            f.name: _jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)
        }
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, bool) or obj is None or isinstance(obj, (int, str)):
        return obj
    if isinstance(obj, float):
        if not math.isfinite(obj):
            raise ValueError(f"non-finite float {obj!r} cannot enter a config or key")
        return obj
    if hasattr(obj, "item") and callable(obj.item):  # numpy scalar
        return _jsonable(obj.item())
    raise TypeError(f"cannot put {type(obj).__name__} into canonical JSON: {obj!r}")


def canonical_json(obj: Any) -> str:
    """Deterministic JSON: sorted keys, no spaces, floats via repr, tuples as lists."""
    return json.dumps(
        _jsonable(obj), sort_keys=True, separators=(",", ":"), allow_nan=False
    )


def _coerce(value: Any, hint: Any, where: str) -> Any:
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if hint is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        errors = []
        for arg in args:
            if arg is type(None):
                if value is None:
                    return None
                continue
            try:
                return _coerce(value, arg, where)
            except InputError as exc:
                errors.append(str(exc))
        raise InputError(errors[-1] if errors else f"{where}: bad value {value!r}")
    if origin is typing.Literal:
        if value not in args:
            raise InputError(f"{where} = {value!r}: must be one of {list(args)}")
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise InputError(
                f'{where} = {value!r}: expected a list, e.g. --set \'{where}=["a", "b"]\''
            )
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], where) for v in value)
        if len(args) != len(value):
            raise InputError(f"{where} = {value!r}: expected {len(args)} values")
        return tuple(_coerce(v, a, where) for v, a in zip(value, args, strict=True))
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(f"{where} = {value!r}: expected a number")
        return float(value)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(f"{where} = {value!r}: expected an integer")
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise InputError(f"{where} = {value!r}: expected true or false")
        return value
    if hint is str:
        if not isinstance(value, str):
            raise InputError(f"{where} = {value!r}: expected a string")
        return value
    return value


# The range of a numeric config value, by its key (in any section). Every other
# number must be finite and >= 0: no key of ptovs takes a negative value or NaN.
AT_LEAST_ONE = frozenset(
    "iterations epochs batch_size n_appearances crop_size sam_points_per_side "
    "max_image_size max_num_features max_gaussians densify_every sh_increase_every "
    "opacity_reset_every checkpoint_every retrieval_k min_num_matches "
    "min_pose_inliers cache_mb window_rows patience stop_patience table_size "
    "downscale".split()
)
UNIT = frozenset(  # fractions and probabilities: [0, 1]
    "quality_quantile tau_u heldout_fraction test_fraction percent_dense "
    "prune_opacity prune_unseen repeat_threshold min_alpha min_opacity "
    "min_visibility".split()
)
BELOW_ONE = frozenset({"threshold"})  # [0, 1): at 1 nothing can pass
SIGNED = {"import_iteration": -1}  # -1: the latest
# 0 means "the stage's own choice" here (the encoder's input size, the runtime's batch)
ZERO_IS_AUTO = frozenset({"extract-features.crop_size", "extract-features.batch_size"})


def check_range(key: str, value: Any) -> None:
    """Refuse a number no stage can use (`AT_LEAST_ONE`, `UNIT`, `BELOW_ONE`,
    `SIGNED`; otherwise finite and >= 0), naming the key and its range."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return
    name = key.rsplit(".", 1)[-1]
    lo, hi, why = 0, None, ">= 0"
    if name in AT_LEAST_ONE and key not in ZERO_IS_AUTO:
        lo, why = 1, ">= 1"
    elif name in UNIT:
        hi, why = 1.0, "between 0 and 1"
    elif name in BELOW_ONE:
        hi, why = math.nextafter(1.0, 0.0), "at least 0 and below 1"
    elif name in SIGNED:
        lo, why = SIGNED[name], f">= {SIGNED[name]}"
    if not math.isfinite(value) or value < lo or (hi is not None and value > hi):
        raise InputError(f"{key} = {value!r}: must be {why}")


def build_config(cls: type, section: Mapping[str, Any] | None, name: str) -> Any:
    """Instantiate a frozen config dataclass from a config section.

    Unknown keys and wrongly typed values are errors that list the valid keys.
    """
    section = dict(section or {})
    hints = typing.get_type_hints(cls)
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(section) - known)
    if unknown:
        raise InputError(
            f"[{name}] has no key {unknown[0]!r}{did_you_mean(unknown[0], sorted(known))}"
            "; valid keys: "
            f"{', '.join(sorted(known))}"
        )
    kwargs = {k: _coerce(v, hints[k], f"{name}.{k}") for k, v in section.items()}
    for k, v in kwargs.items():
        check_range(f"{name}.{k}", v)
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise InputError(f"[{name}]: {exc}") from None


def check_config(config: Mapping[str, Any], origin: str = "the config") -> None:
    """Every section and key of a merged config (`--config` file plus the group's
    `--set` items), checked before anything runs: an unknown section or key, or a
    value of the wrong type, is an InputError with the nearest valid name."""
    sections = section_names()
    for name, section in config.items():
        if name not in sections:
            raise InputError(
                f"{origin}: unknown section [{name}]"
                + did_you_mean(name, sections, "[{}]")
                + f"; sections: {', '.join(sections)}"
            )
        if not isinstance(section, Mapping):
            raise InputError(
                f"{origin}: [{name}] must be a table of KEY = VALUE, got {section!r}"
            )
        keys = config_keys(name)
        for key in section:
            if key not in keys:
                raise InputError(
                    f"{origin}: [{name}] has no key {key!r}"
                    + did_you_mean(key, keys)
                    + f"; valid keys: {', '.join(sorted(keys))}"
                )
        build_config(config_class(name), section, name)  # the values' types
