"""pipeline.grid: Cartesian product, dependent axes, include/exclude filters, labels, clear errors."""
import pytest

from pipeline.grid import Axis, GridError, expand


def test_product_is_complete_first_axis_slowest():
    cells = expand([Axis("a", (1, 2)), Axis("b", ("x", "y", "z"))])
    assert [c.as_dict() for c in cells] == [{"a": a, "b": b} for a in (1, 2) for b in "xyz"]
    assert cells[0].label() == "a=1, b=x" and cells[-1]["b"] == "z"


def test_dependent_axis_takes_values_from_earlier_coordinates():
    sizes = {"red": (1,), "blue": (2, 3)}
    cells = expand([Axis("colour", ("red", "blue")), Axis("size", lambda c: sizes[c["colour"]]),
                    Axis("rate", (0.1, 0.3))])
    assert [(c["colour"], c["size"]) for c in cells] == [("red", 1)] * 2 + [("blue", 2)] * 2 + [("blue", 3)] * 2
    assert len(cells) == 2 * (1 + 2)


def test_include_keeps_matching_cells_then_exclude_drops():
    axes = [Axis("a", (1, 2, 3)), Axis("b", (0.1, 0.3))]
    assert {c["a"] for c in expand(axes, include=[{"a": [1, 3]}])} == {1, 3}
    kept = expand(axes, include=[{"a": 1}, {"b": 0.3}], exclude=[{"a": 3, "b": 0.3}])
    assert sorted((c["a"], c["b"]) for c in kept) == [(1, 0.1), (1, 0.3), (2, 0.3)]
    # numbers compare by value (TOML 1 vs 1.0), booleans never equal numbers
    assert len(expand(axes, exclude=[{"a": 1.0}])) == 4
    flags = expand([Axis("f", (True, 1))], exclude=[{"f": True}])
    assert [c["f"] for c in flags] == [1]


@pytest.mark.parametrize("kwargs, fragment", [
    ({"include": [{"c": 1}]}, "unknown axis 'c'"),
    ({"exclude": [{"a": 5}]}, "never takes the value 5"),
    ({"exclude": [{"a": [1, 2, 3]}]}, "leave no cell"),
    ({"include": [{}]}, "non-empty table"),
])
def test_bad_filters_are_refused_naming_axis_and_values(kwargs, fragment):
    with pytest.raises(GridError, match=fragment):
        expand([Axis("a", (1, 2, 3)), Axis("b", ("x",))], **kwargs)


def test_duplicate_or_empty_axes_are_refused():
    with pytest.raises(GridError, match="unique"):
        expand([Axis("a", (1,)), Axis("a", (2,))])
    with pytest.raises(GridError, match="no values"):
        expand([Axis("a", ())])
