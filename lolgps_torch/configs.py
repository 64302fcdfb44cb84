"""Config dataclasses back from their saved form (the inverse of ``dataclasses.asdict``)."""

from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any, TypeVar

from lolgps_torch.errors import LolgpsError

Config = TypeVar("Config")


def _value(kind: Any, value: Any) -> Any:
    """``value`` as the field type ``kind`` wants it: nested dataclasses rebuilt, JSON lists
    back to tuples."""
    if value is None:
        return None
    options = typing.get_args(kind) if isinstance(kind, types.UnionType) else (kind,)
    for option in options:
        if dataclasses.is_dataclass(option) and isinstance(value, dict):
            return from_dict(option, value)  # type: ignore[arg-type]
        if typing.get_origin(option) is tuple and isinstance(value, list):
            return tuple(value)
    return value


def from_dict(cls: type[Config], data: dict[str, Any]) -> Config:
    """An instance of the dataclass ``cls`` from ``asdict(instance)`` as saved in JSON; keys
    the class does not know are a :class:`LolgpsError`."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = set(data) - names
    if unknown:
        raise LolgpsError(f"{cls.__name__}: unknown settings {sorted(unknown)}")
    return cls(**{k: _value(hints[k], v) for k, v in data.items()})
