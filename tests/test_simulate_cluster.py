"""The cluster simulator (benchmarks.simulate_cluster): list scheduling against the critical path."""
from __future__ import annotations

from benchmarks.simulate_cluster import SimStep, critical_path, simulate, workflow_steps


def diamond() -> list[SimStep]:
    return [SimStep("a", "a", "scene", 2, 10.0), SimStep("b", "b", "edit", 1, 30.0, ["a"]),
            SimStep("c", "c", "edit", 1, 20.0, ["a"]), SimStep("d", "d", "evaluate", 1, 5.0, ["b", "c"])]


def test_critical_path_and_makespans():
    steps = diamond()
    assert critical_path(steps) == (45.0, ["a", "b", "d"])
    assert simulate(steps, nodes=1, cores=2) == 45.0           # b and c side by side
    assert simulate([SimStep("x", "x", "edit", 1, 3.0), SimStep("y", "y", "edit", 1, 4.0)], nodes=1, cores=1) == 7.0
    assert simulate([SimStep("x", "x", "edit", 1, 3.0), SimStep("y", "y", "edit", 1, 4.0)], nodes=2, cores=1) == 4.0


def test_a_step_waits_for_a_node_with_enough_free_cpus_without_blocking_smaller_ones():
    # The 2-CPU step cannot start while the long 1-CPU step holds half the node; the short ones overtake it.
    steps = [SimStep("long", "long", "edit", 1, 100.0), SimStep("wide", "wide", "fit", 2, 10.0),
             SimStep("short", "short", "edit", 1, 5.0)]
    assert simulate(steps, nodes=1, cores=2) == 110.0
    assert simulate(steps, nodes=2, cores=2) == 100.0


def test_the_comparison_workflow_dag():
    steps = workflow_steps("workflows/comparison.toml", [])
    assert len(steps) == 209
    path, chain = critical_path(steps)
    assert chain[0].startswith("scene[") and chain[-1].startswith("evaluate[") and "DualNeRF" in chain[-1]
    assert abs(path - (17 + 15 + 110 + 455 + 19)) < 1e-6
    assert simulate(steps, nodes=64, cores=8) == path
