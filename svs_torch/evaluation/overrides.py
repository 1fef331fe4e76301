"""Named presets and dotted-path overrides of :class:`~svs_torch.pipeline.PipelineConfig`: one syntax for
``--set KEY=VALUE``, configuration files and sweep grids.

A key is the path of a field through the nested frozen dataclasses, e.g. ``segmentation.kernel_size``,
``surf.metric_threshold``, ``max_ratio``, ``dense.window_size``, ``refine_matches.min_correlation``. Each value is
checked against the field's declared type (bool, int, float — finite —, str, ``Literal`` choices, optional
values, ``tuple[float, float]``) and then by the dataclass itself (its ``__post_init__``, once, with its final
values: :mod:`.config_tree`), so a bad key or value is an :class:`~svs_torch.core.checks.InputError` naming the key
before any work starts. A field that holds an optional configuration (``refine_matches``) takes ``false`` /
``"none"`` (off) or ``true`` (its defaults), and setting one of its sub-fields turns it on from its defaults. New
configurations are new dataclasses; the presets are never modified.

Configuration file (TOML)::

    preset = "paper"          # optional: "default" (PipelineConfig()) or "paper" (PipelineConfig.paper())
    max_ratio = 0.7           # top-level keys, quoted dotted keys and tables are all dotted paths:
    "surf.num_octaves" = 3
    [segmentation]
    kernel_size = 7
    [set]                     # a sweep file's fixed settings are read the same way (one format for both)
    "ransac_threshold_px" = 0.5

A sweep file (:mod:`.sweep`) works as a configuration file: its ``preset`` and ``[set]`` apply, its ``paths``,
``size`` and ``batch_size`` are named as not used, and a ``[grid]`` or ``[[configs]]`` (several configurations)
is an error. A sweep file likewise takes top-level parameters as fixed settings. A setting only the dense range
rule reads, given under the paper's rule, or only the nearness segmenter, under another, is said to have no effect
(:mod:`.inert_settings`).
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import itertools
import math
import tomllib
import types
import typing
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from ..core.checks import InputError, check_instance, nesting_depth
from ..core.files import check_path_given, path_kind
from ..pipeline import PipelineConfig
from ..segmentation.network_files import check_weights_file
from .config_tree import ON, ConfigBuildError, build_config, dataclass_of, refused_keys
from .inert_settings import warn_inert_overrides

__all__ = [
    "LABEL_SEPARATOR", "PRESETS", "apply_overrides", "config_to_dict", "describe_overrides", "expand_grid",
    "flatten_table", "load_config_file", "merge_fixed", "merge_labels", "merge_overrides", "parameter_types",
    "parse_assignment", "preset_config", "resolve_config",
]

#: The named starting points: the product's best measured defaults and the paper's steps as published.
PRESETS: dict[str, Callable[[], PipelineConfig]] = {"default": PipelineConfig, "paper": PipelineConfig.paper}

_NONE_WORDS = ("none", "null", "off")
_TRUE_WORDS = ("true", "yes", "on")
_FALSE_WORDS = ("false", "no", "off")


def preset_config(name: str, source: str = "preset") -> PipelineConfig:
    """The configuration of a named preset (``"default"`` or ``"paper"``)."""
    if name not in PRESETS:
        raise InputError(f"{source}: expected one of {', '.join(map(repr, PRESETS))}, got {name!r}")
    return PRESETS[name]()


def _is_optional(hint: Any) -> bool:
    return typing.get_origin(hint) in (typing.Union, types.UnionType) and type(None) in typing.get_args(hint)


def parameter_types(cls: type = PipelineConfig, prefix: str = "") -> dict[str, Any]:
    """Every dotted key of ``cls`` (leaves and nested configurations) with its declared type (a new dict; the
    types are read once a process: ``typing.get_type_hints`` took 6 of the 8 ms a sweep's configuration took to
    check, so a grid of 10 000 points checked for over a minute before its first task)."""
    return dict(_parameter_types(cls, prefix))


@functools.lru_cache(maxsize=None)
def _parameter_types(cls: type, prefix: str) -> dict[str, Any]:
    keys: dict[str, Any] = {}
    hints = typing.get_type_hints(cls)
    for field in dataclasses.fields(cls):
        key, hint = prefix + field.name, hints[field.name]
        keys[key] = hint
        nested = dataclass_of(hint)
        if nested is not None:
            keys.update(_parameter_types(nested, key + "."))
    return keys


def _describe_type(hint: Any) -> str:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if dataclass_of(hint) is not None:
        return ("true or false (on with its defaults, or off)" if _is_optional(hint)
                else "its fields as dotted keys (section.field = value)")
    if origin is typing.Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_describe_type(a) for a in args)
    if origin is tuple:
        return f"a list of {len(args)} numbers"
    if hint is type(None):
        return "none"
    return {bool: "true or false", int: "an integer", float: "a finite number", str: "a string"}.get(hint, str(hint))


class _Mismatch(Exception):
    """A value that does not fit a type (turned into an InputError naming the key)."""


def _coerce(value: Any, hint: Any) -> Any:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is typing.Literal:
        if value in args and type(value) is type(args[args.index(value)]):
            return value
        raise _Mismatch
    if origin in (typing.Union, types.UnionType):
        for arg in (a for a in args if a is not type(None)):
            try:
                return _coerce(value, arg)
            except _Mismatch:
                pass
        if type(None) in args and (value is None or (isinstance(value, str) and value.lower() in _NONE_WORDS)):
            return None
        raise _Mismatch
    if origin is tuple:
        if isinstance(value, str):
            value = [part.strip() for part in value.split(",")]
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            raise _Mismatch
        return tuple(_coerce(item, arg) for item, arg in zip(value, args))
    if hint is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in _TRUE_WORDS + _FALSE_WORDS:
            return value.lower() in _TRUE_WORDS
        raise _Mismatch
    if hint is int:
        if isinstance(value, str):
            try:
                value = int(value)
            except ValueError:
                raise _Mismatch from None
        if isinstance(value, bool) or not isinstance(value, int):
            raise _Mismatch
        return value
    if hint is float:
        if isinstance(value, str):
            try:
                value = float(value)
            except ValueError:
                raise _Mismatch from None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise _Mismatch
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise _Mismatch
        return value
    raise _Mismatch


def _unknown_key(key: str, source: str) -> InputError:
    close = difflib.get_close_matches(key, list(parameter_types()), n=3, cutoff=0.6)
    hint = f" (did you mean {', '.join(close)}?)" if close else " ('svs-depth eval --help' lists the sections)"
    return InputError(f"{source}: unknown parameter {key!r}{hint}")


def _leaf_value(key: str, value: Any, hint: Any) -> Any:
    """The checked value of ``key``; an optional configuration takes true (:data:`ON`) / false / none."""
    nested = dataclass_of(hint)
    if nested is None:
        return _coerce(value, hint)
    if isinstance(value, str):
        value = value.lower()
        value = True if value in _TRUE_WORDS else False if value in _FALSE_WORDS + _NONE_WORDS else value
    if value is None or value is False:
        if not _is_optional(hint):
            raise _Mismatch
        return None
    if value is True:
        return ON
    raise _Mismatch


def apply_overrides(config: PipelineConfig, overrides: Mapping[str, Any], source: str = "set") -> PipelineConfig:
    """``config`` with each dotted ``key: value`` of ``overrides`` set in order, each nested configuration then
    checked once with its final values (:mod:`.config_tree`: the order of two keys a check relates never matters).

    Raises:
        InputError: ``source: unknown parameter 'key'`` (with close matches), or ``source: key: expected
            <type>, got <value>``, or the dataclass's own check of its final values, named by the keys that set them.
    """
    check_instance(config, "config", PipelineConfig)
    known = parameter_types()
    checked = []
    for key, value in overrides.items():
        if key not in known:
            raise _unknown_key(key, source)
        try:
            checked.append((key, _leaf_value(key, value, known[key])))
        except _Mismatch:
            raise InputError(f"{source}: {key}: expected {_describe_type(known[key])}, got {value!r}") from None
    try:
        built = build_config(config, checked)
    except ConfigBuildError as failed:
        keys = ", ".join(f"{key} = {overrides[key]!r}" for key in refused_keys(overrides, failed))
        raise InputError(f"{source}: {keys}: {failed.error}") from None
    if "segmentation.segmenter" in overrides:
        # Read now: a bad weights file made every pair of an eval or a sweep an ERROR row, exit status 0 (an audit).
        try:
            check_weights_file(built.segmentation.segmenter)
        except InputError as error:
            raise InputError(f"{source}: segmentation.segmenter = {overrides['segmentation.segmenter']!r}: "
                             f"{error}") from None
    return built


def parse_assignment(text: str, source: str = "--set") -> tuple[str, Any]:
    """``"KEY=VALUE"`` → ``(key, value)``; VALUE is read as a TOML value where it is one (``0.7``, ``true``,
    ``[10, 90]``, ``"text"``), else taken as a bare string (``paper``, ``none``)."""
    key, sep, raw = text.partition("=")
    key, raw = key.strip(), raw.strip()
    if not sep or not key or not raw:
        raise InputError(f"{source}: expected KEY=VALUE such as segmentation.kernel_size=7, got {text!r}")
    try:
        value = tomllib.loads(f"value = {raw}")["value"]
    except tomllib.TOMLDecodeError:
        value = raw
    except RecursionError:  # (nested thousands deep: an internal RecursionError, an audit)
        raise InputError(f"{source}: {key}: expected a setting's value, got one nested too deep") from None
    return key, value


def flatten_table(table: Mapping[str, Any], prefix: str = "", source: str = "table") -> dict[str, Any]:
    """A TOML table with nested tables (``[segmentation] kernel_size = 7``) as dotted keys. An empty table stays a
    value (``[exposure]`` alone: an error naming it, not silently nothing), and a parameter given twice, as a quoted
    dotted key and in a table, is an InputError starting with ``source`` (one of the two was silently dropped)."""
    flat: dict[str, Any] = {}
    for key, value in table.items():
        nested = isinstance(value, Mapping) and value
        for name, item in (flatten_table(value, f"{prefix}{key}.", source).items() if nested
                           else [(prefix + key, dict(value) if isinstance(value, Mapping) else value)]):
            if name in flat:
                raise InputError(f"{source}: {name}: given twice (a quoted dotted key and a table's key name the "
                                 f"same parameter); expected it once")
            flat[name] = item
    return flat


def merge_fixed(top_level: Mapping[str, Any], fixed: Mapping[str, Any], source: str) -> dict[str, Any]:
    """A file's top-level parameters, then its ``[set]``: one parameter in both is an InputError (``[set]`` won in
    silence)."""
    both = sorted(set(top_level) & set(fixed))
    if both:
        raise InputError(f"{source}: {', '.join(both)}: given both at the top level and in [set]; expected each once")
    return merge_overrides(top_level, fixed)


def read_toml(path: str | Path, name: str) -> dict[str, Any]:
    """A TOML file as a dict; a missing, unreadable or malformed file is an InputError naming ``name`` and it."""
    path = Path(path)
    label = name if name == str(path) else f"{name}: {path}"
    if (kind := path_kind(path, name)) != "file":  # (a name too long: "File name too long" alone, exit 1; an audit)
        got = {"folder": "a folder", "other": "a special file"}.get(kind, "no file")
        raise InputError(f"{label}: expected a TOML file, got {got}")
    try:
        table = tomllib.loads(path.read_bytes().decode("utf-8-sig"))  # a Windows editor's byte-order mark: no text
    except UnicodeDecodeError:
        raise InputError(f"{label}: expected a UTF-8 TOML file") from None
    except tomllib.TOMLDecodeError as error:
        raise InputError(f"{label}: not valid TOML: {error}") from None
    except RecursionError:  # arrays or inline tables nested thousands deep: the parser's (an audit)
        table = None
    except OSError as error:
        raise InputError(f"{label}: cannot read it: {error.strerror or error}") from None
    if table is None or nesting_depth(table) > 32:  # (a header [a.a.a...] of thousands: flatten_table's recursion)
        raise InputError(f"{label}: tables or arrays nested too deep to be a configuration (over 32 levels)")
    return table


#: The keys of a sweep file that say what to run on, not how: a configuration file may carry them (one TOML
#: format for both); a command given it as ``--config`` says it does not use them.
SWEEP_RUN_KEYS = ("paths", "size", "batch_size")


def load_config_file(path: str | Path, name: str = "--config") -> tuple[str, dict[str, Any]]:
    """``(preset name, dotted overrides)`` of a configuration file (module docstring); not yet applied."""
    check_path_given(path, name, "a configuration file name")  # ('' is '.': "got a folder", an audit)
    table = read_toml(path, name)
    preset = table.pop("preset", "default")
    if not isinstance(preset, str):
        raise InputError(f"{name}: {path}: preset: expected one of {', '.join(map(repr, PRESETS))}, got {preset!r}")
    fixed = table.pop("set", {})  # a sweep file's fixed settings: one format for both
    if not isinstance(fixed, Mapping):
        raise InputError(f"{name}: {path}: set: expected a table of parameters, got {fixed!r}")
    for key in ("grid", "configs"):
        if key in table:
            raise InputError(f"{name}: {path}: {key}: a sweep's {key} makes several configurations and this runs "
                             f"one (svs-depth sweep runs them; here only preset and [set] apply)")
    unused = [key for key in SWEEP_RUN_KEYS if key in table]
    for key in unused:
        del table[key]
    if unused:  # said, not silently dropped: the command's own PATH and options decide these
        warnings.warn(f"{name}: {path}: the sweep's {', '.join(unused)} not used (this command's PATH, --size and "
                      f"--batch-size apply)", stacklevel=2)
    source = f"{name}: {path}"
    return preset, merge_fixed(flatten_table(table, source=source), flatten_table(fixed, source=f"{source}: set"),
                               source)


def resolve_config(preset: str = "default", config_file: str | Path | None = None,
                   assignments: tuple[str, ...] | list[str] = ()) -> tuple[PipelineConfig, str, dict[str, Any]]:
    """The configuration of ``--preset`` or ``--config FILE``, then each ``--set KEY=VALUE`` (later ones win).

    Returns ``(config, preset name, all overrides applied)``.
    """
    overrides: dict[str, Any] = {}
    if config_file is not None:
        preset, from_file = load_config_file(config_file)
        base = preset_config(preset, f"--config: {config_file}: preset")
        base = apply_overrides(base, from_file, f"--config: {config_file}")
        overrides.update(from_file)
    else:
        base = preset_config(preset, "--preset")
    sets = merge_overrides(*({key: value} for key, value in map(parse_assignment, assignments)))
    config = apply_overrides(base, sets, "--set")
    for source, given in ((f"--config: {config_file}", overrides), ("--set", sets)):
        warn_inert_overrides([(config, given)], source)  # judged on the configuration that runs
    return config, preset, merge_overrides(overrides, sets)


def merge_overrides(*mappings: Mapping[str, Any]) -> dict[str, Any]:
    """The overrides of ``mappings`` one after another, as one dict in which a key assigned again moves to the end:
    applied in its order (as :func:`apply_overrides` does), it gives what the mappings give in turn. A plain merge
    keeps a key where it first came with its last value, so ``a.b=1``, ``a=none``, ``a.b=2`` would apply ``a.b=2``
    before ``a=none``, and a stored configuration would replay into another one than ran."""
    ordered: dict[str, Any] = {}
    for mapping in mappings:
        for key, value in mapping.items():
            ordered.pop(key, None)
            ordered[key] = value
    return ordered


#: The most combinations a sweep's grid may hold (each runs the pipeline over every listed pair: 10 000 points over
#: the 45 shared pairs is 450 000 pipeline runs, 5 to 15 hours on two cores).
MAX_GRID_POINTS = 10_000


def expand_grid(grid: Mapping[str, Any], source: str = "grid") -> list[dict[str, Any]]:
    """Every combination of a grid ``{key: [values...]}``, the first key varying slowest."""
    for key, values in grid.items():
        if not isinstance(values, list) or not values:
            raise InputError(f"{source}: {key}: expected a non-empty list of values, got {values!r}")
    keys = list(grid)
    count = math.prod(len(grid[k]) for k in keys)
    if count > MAX_GRID_POINTS:  # checked before expanding: 10^6 points were checked for hours, silently
        raise InputError(f"{source}: {' x '.join(str(len(grid[k])) for k in keys)} = {count} combinations, at most "
                         f"{MAX_GRID_POINTS}; sweep fewer values, or split the grid into several sweeps")
    return [dict(zip(keys, combination)) for combination in itertools.product(*(grid[k] for k in keys))]


#: Between the labels of one configuration reached by several descriptions (``max_ratio=0.8`` is the default's value).
LABEL_SEPARATOR = " | "


def merge_labels(*labels: str) -> str:
    """One label for a configuration several descriptions reach: each distinct description once, in order,
    joined by :data:`LABEL_SEPARATOR` (a results summary then shows every name it ran under, not the first)."""
    seen: dict[str, None] = {}
    for label in labels:
        for part in label.split(LABEL_SEPARATOR):
            seen.setdefault(part, None)
    return LABEL_SEPARATOR.join(seen)


def describe_overrides(overrides: Mapping[str, Any]) -> str:
    """``"segmentation.kernel_size=3 max_ratio=0.6"``; ``"(preset)"`` when nothing is overridden."""
    return " ".join(f"{key}={value}" for key, value in overrides.items()) or "(preset)"


def config_to_dict(config: PipelineConfig) -> dict[str, Any]:
    """The whole configuration as JSON-ready nested dicts (tuples as lists)."""
    check_instance(config, "config", PipelineConfig)

    def plain(value: Any) -> Any:
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        return value

    return plain(dataclasses.asdict(config))
