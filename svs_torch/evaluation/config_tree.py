"""Dotted overrides applied to a configuration as a whole (:func:`~.overrides.apply_overrides`): every value is set
first, in order, and each nested dataclass is then built once, with its final values, so its own check
(``__post_init__``) sees what the user asked for. Applied one at a time, ``segmentation.ground.min_camera_height_m=4``
then ``...max_camera_height_m=5`` failed on the way, as "expected 0 < min < max, got 4.0, 3.0" (3 the default
maximum the next key replaced), and only the reverse order ran (an audit of hostile configuration values).
"""

from __future__ import annotations

import dataclasses
import re
import typing
from collections.abc import Sequence
from typing import Any

__all__ = ["ON", "ConfigBuildError", "build_config", "dataclass_of", "refused_keys"]

#: The value that turns an optional configuration on: kept as it is where on, its defaults where off.
ON = object()


def dataclass_of(hint: Any) -> type | None:
    """The dataclass a field holds (also through ``X | None``), or None."""
    if dataclasses.is_dataclass(hint):
        return hint
    for arg in typing.get_args(hint):
        if dataclasses.is_dataclass(arg):
            return arg
    return None


class ConfigBuildError(Exception):
    """The dataclass at ``prefix`` (``""``: the whole configuration, ``"segmentation.ground."``) refused its final
    values with ``error``."""

    def __init__(self, prefix: str, error: Exception) -> None:
        super().__init__(str(error))
        self.prefix, self.error = prefix, error


class _Draft:
    """A dataclass's field values while overrides are set (nested ones drafts where a key reaches into them)."""

    def __init__(self, cls: type, values: dict[str, Any]) -> None:
        self.cls, self.values = cls, values

    @classmethod
    def of(cls, instance: Any) -> _Draft:
        return cls(type(instance), {f.name: getattr(instance, f.name) for f in dataclasses.fields(instance)})


def _set(draft: _Draft, path: Sequence[str], value: Any) -> None:
    name, current = path[0], draft.values[path[0]]
    if len(path) == 1:
        draft.values[name] = (current if current is not None else _default(draft, name)) if value is ON else value
        return
    if current is None:  # an optional configuration that is off: a sub-field turns it on from its defaults
        current = _default(draft, name)
    inner = current if isinstance(current, _Draft) else _Draft.of(current)
    draft.values[name] = inner
    _set(inner, path[1:], value)


def _default(draft: _Draft, name: str) -> Any:
    return dataclass_of(typing.get_type_hints(draft.cls)[name])()


def _build(value: Any, prefix: str) -> Any:
    if not isinstance(value, _Draft):
        return value
    values = {name: _build(inner, f"{prefix}{name}.") for name, inner in value.values.items()}
    try:
        return value.cls(**values)
    except (ValueError, TypeError) as error:  # its own check: an InputError, or a comparison's TypeError
        raise ConfigBuildError(prefix, error) from None


def build_config(config: Any, assignments: Sequence[tuple[str, Any]]) -> Any:
    """``config`` with each ``(dotted key, checked value)`` set in order (:data:`ON`: an optional configuration on),
    each touched dataclass built once with its final values. Raises :class:`ConfigBuildError` naming the first
    (innermost) dataclass that refuses them; ``config`` itself is never changed."""
    if not assignments:
        return config
    root = _Draft.of(config)
    for key, value in assignments:
        _set(root, key.split("."), value)
    return _build(root, "")


def refused_keys(keys: Sequence[str], failed: ConfigBuildError) -> list[str]:
    """The keys a refusal is about: those under the refusing dataclass that its message names (relative to it, as
    its checks name fields: ``differentiable: needs depth.rule 'dense'`` names ``depth.rule``), else every key under
    it (``--set max_ratio=0.7 --set depth.rule=paper`` on a differentiable configuration names depth.rule, not
    max_ratio)."""
    under = [key for key in keys if key.startswith(failed.prefix)]
    message = str(failed.error)
    named = [key for key in under if re.search(rf"(?<![\w.]){re.escape(key[len(failed.prefix):])}(?!\w)", message)]
    return named or under
