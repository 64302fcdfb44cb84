"""Layers point down: no module imports from its own layer's other packages or above, and no
module imports one that imports it back."""

from __future__ import annotations

import graphlib

from lolgps_torch.layers import imports, module_imports, rank


def test_every_import_points_to_a_lower_layer() -> None:
    edges = imports()
    assert ("lolgps", "data") in edges  # the check sees real imports
    upward = [(s, t) for s, t in edges if rank(t) >= rank(s)]
    assert upward == []


def test_no_module_imports_itself_through_others() -> None:
    graph: dict[str, set[str]] = {}
    for source, target in module_imports():
        graph.setdefault(source, set()).add(target)
    assert ("lolgps_torch.sim.rollout", "lolgps_torch.sim.engines") in module_imports()
    tuple(graphlib.TopologicalSorter(graph).static_order())  # CycleError names a cycle
