"""Canonical JSON: one spelling per value, so equal parameters always hash to the same key.

Rules (why: a key must not change when a user writes `1` instead of `1.0`, `0.1` instead of `1e-1`,
or lists parameters in another order):
- mapping keys are sorted; tuples and lists are both JSON arrays; sets become sorted arrays;
- an integral float becomes an int (1.0 == 1); other floats use Python's shortest round-trip repr,
  which is what `json` writes, so 0.1 and 1e-1 (the same double) are spelled identically;
- NaN and infinities, which JSON cannot hold, become {"float": "nan" | "inf" | "-inf"};
- dataclass instances become their field mappings, paths become POSIX strings, enums their value.
"""
from __future__ import annotations

import dataclasses
import enum
import hashlib
import json
import math
from collections.abc import Mapping
from pathlib import PurePath
from typing import Any


def canonical_value(value: Any, where: str = "value") -> Any:
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        if math.isnan(value):
            return {"float": "nan"}
        if math.isinf(value):
            return {"float": "inf" if value > 0 else "-inf"}
        return int(value) if value.is_integer() else value
    if isinstance(value, enum.Enum):
        return canonical_value(value.value, where)
    if isinstance(value, PurePath):
        return value.as_posix()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: canonical_value(getattr(value, f.name), f"{where}.{f.name}")
                for f in dataclasses.fields(value)}
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise TypeError(f"{where}: mapping keys must be strings, got {k!r}")
            out[k] = canonical_value(v, f"{where}.{k}")
        return out
    if isinstance(value, (list, tuple)):
        return [canonical_value(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, (set, frozenset)):
        items = [canonical_value(v, where) for v in value]
        return sorted(items, key=lambda item: json.dumps(item, sort_keys=True))
    # numpy scalars and similar expose .item(); anything else has no stable spelling.
    if hasattr(value, "item") and callable(value.item):
        return canonical_value(value.item(), where)
    raise TypeError(f"{where}: {type(value).__name__} {value!r} has no canonical JSON form")


def canonical_json(value: Any) -> str:
    return json.dumps(canonical_value(value), sort_keys=True, separators=(",", ":"),
                      ensure_ascii=False, allow_nan=False)


def sha256_of(value: Any) -> str:
    return hashlib.sha256(canonical_json(value).encode("utf-8")).hexdigest()
