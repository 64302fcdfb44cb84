"""Layers point down: no module imports from its own layer's other packages or above."""

from __future__ import annotations

from lolgps_torch.layers import imports, rank


def test_every_import_points_to_a_lower_layer() -> None:
    edges = imports()
    assert ("lolgps", "data") in edges  # the check sees real imports
    upward = [(s, t) for s, t in edges if rank(t) >= rank(s)]
    assert upward == []
