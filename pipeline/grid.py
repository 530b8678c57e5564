"""Experiment grids: the Cartesian product of named axes, with include/exclude filters and cell labels.

    axes = [Axis("colour", ("red", "blue")),
            Axis("size", lambda cell: SIZES[cell["colour"]]),     # values may depend on earlier axes
            Axis("rate", (0.1, 0.3))]
    cells = expand(axes, include=[{"colour": "red"}], exclude=[{"size": 3, "rate": 0.3}])
    cells[0]["rate"], cells[0].label()  ->  0.1, "colour=red, size=1, rate=0.1"

Filter semantics (one rule, as in Hydra/W&B sweeps): a filter is a mapping axis name -> value or list of
values; a cell matches it when, for every name in it, the cell's value equals the value (or one of the
list). With `include` given, a cell is kept only if it matches at least one include filter; then every
cell matching any exclude filter is dropped. A filter naming an unknown axis, or a value that no cell of
that axis can take, is a GridError (a typo must not silently select nothing).

The engine knows nothing of what the axes mean; the application turns each cell into steps.
"""
from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from pipeline.errors import UserError


class GridError(UserError):
    """A grid that cannot be expanded (bad filter, empty axis); the message names the axis and values."""


Values = Sequence[Any] | Callable[["Cell"], Sequence[Any]]


@dataclass(frozen=True)
class Axis:
    name: str
    values: Values                       # the values, or a function of the cell's earlier coordinates

    def values_for(self, partial: Cell) -> tuple:
        values = self.values(partial) if callable(self.values) else self.values
        values = tuple(values)
        if not values:
            raise GridError(f"grid axis '{self.name}' has no values"
                            + (f" for {partial.label()}" if partial.coords else "") + ".")
        return values


@dataclass(frozen=True)
class Cell:
    """One point of the grid: (axis name, value) pairs in axis order."""

    coords: tuple[tuple[str, Any], ...] = ()

    def __getitem__(self, name: str) -> Any:
        for key, value in self.coords:
            if key == name:
                return value
        raise KeyError(name)

    def get(self, name: str, default: Any = None) -> Any:
        try:
            return self[name]
        except KeyError:
            return default

    def as_dict(self) -> dict[str, Any]:
        return dict(self.coords)

    def extended(self, name: str, value: Any) -> Cell:
        return Cell(self.coords + ((name, value),))

    def label(self, names: Sequence[str] | None = None) -> str:
        """"a=1, b=x" over `names` (default: every axis)."""
        shown = self.coords if names is None else [(k, v) for k, v in self.coords if k in names]
        return ", ".join(f"{k}={format_value(v)}" for k, v in shown)


def format_value(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(format_value(v) for v in value) + "]"
    return str(value)


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, bool) or isinstance(b, bool):
        return a is b if isinstance(a, bool) and isinstance(b, bool) else False
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return float(a) == float(b)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


def _matches(cell: Cell, condition: Mapping[str, Any]) -> bool:
    for name, wanted in condition.items():
        value = cell.get(name, _MISSING)
        options = wanted if isinstance(wanted, list) else [wanted]
        if value is _MISSING or not any(_same(value, option) for option in options):
            return False
    return True


_MISSING = object()


def _product(axes: Sequence[Axis]) -> Iterator[Cell]:
    if all(not callable(axis.values) for axis in axes):
        value_lists = [axis.values_for(Cell()) for axis in axes]
        for combo in itertools.product(*value_lists):
            yield Cell(tuple(zip((a.name for a in axes), combo)))
        return

    def walk(index: int, partial: Cell) -> Iterator[Cell]:
        if index == len(axes):
            yield partial
            return
        axis = axes[index]
        for value in axis.values_for(partial):
            yield from walk(index + 1, partial.extended(axis.name, value))

    yield from walk(0, Cell())


def _check_filters(axes: Sequence[Axis], cells: list[Cell], filters: Sequence[Mapping[str, Any]], kind: str,
                   where: str) -> None:
    names = [axis.name for axis in axes]
    seen: dict[str, list] = {name: [] for name in names}
    for cell in cells:
        for name, value in cell.coords:
            if not any(_same(value, v) for v in seen[name]):
                seen[name].append(value)
    for condition in filters:
        if not isinstance(condition, Mapping) or not condition:
            raise GridError(f"{where}: each {kind} filter must be a non-empty table of axis = value(s), "
                            f"got {condition!r}.")
        for name, wanted in condition.items():
            if name not in seen:
                raise GridError(f"{where}: {kind} filter {dict(condition)!r} names unknown axis '{name}'; "
                                f"the axes are: {', '.join(names)}.")
            for option in wanted if isinstance(wanted, list) else [wanted]:
                if not any(_same(option, v) for v in seen[name]):
                    raise GridError(f"{where}: {kind} filter {dict(condition)!r}: axis '{name}' never takes "
                                    f"the value {option!r}; its values are: "
                                    f"{', '.join(format_value(v) for v in seen[name])}.")


def expand(axes: Sequence[Axis], include: Sequence[Mapping[str, Any]] = (),
           exclude: Sequence[Mapping[str, Any]] = (), where: str = "grid") -> list[Cell]:
    """Every cell of the product of `axes` (first axis slowest), filtered; see the module docstring."""
    names = [axis.name for axis in axes]
    if len(set(names)) != len(names):
        raise GridError(f"{where}: axis names must be unique, got {names}.")
    cells = list(_product(axes))
    _check_filters(axes, cells, include, "include", where)
    _check_filters(axes, cells, exclude, "exclude", where)
    if include:
        cells = [c for c in cells if any(_matches(c, f) for f in include)]
    cells = [c for c in cells if not any(_matches(c, f) for f in exclude)]
    if not cells:
        raise GridError(f"{where}: the filters leave no cell of the grid ({' x '.join(names)}).")
    return cells
