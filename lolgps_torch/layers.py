"""The package's layers, bottom to top: a module imports only from its own package or from a
lower layer (checked by tests/test_layers.py)."""

from __future__ import annotations

import ast
from pathlib import Path

LAYERS: tuple[tuple[str, ...], ...] = (
    ("errors", "types", "state", "progress", "layers"),
    ("robot", "controllers", "configs", "cluster"),
    ("sim", "cost", "dynamics", "trajopt"),
    ("policy",),
    ("task",),
    ("gym_env", "arm_probes"),
    ("data",),
    ("lolgps",),
    ("evaluation",),
    ("cli",),
    ("sweep",),
    ("commands",),
    ("__main__",),
)
PACKAGE = Path(__file__).resolve().parent


def unit_of(module: str) -> str:
    """The layer unit of a dotted module name: ``lolgps_torch.sim.world`` -> ``sim``."""
    return module.split(".")[1] if module.count(".") >= 1 else ""


def rank(unit: str) -> int:
    """The layer index of a unit (ValueError for a unit no layer names)."""
    for index, units in enumerate(LAYERS):
        if unit in units:
            return index
    raise ValueError(f"lolgps_torch.{unit} is in no layer")


def imports() -> list[tuple[str, str]]:
    """``(importing unit, imported unit)`` for every ``lolgps_torch`` import in the package."""
    return sorted(
        {(unit_of(s), unit_of(t)) for s, t in module_imports() if unit_of(s) != unit_of(t)}
    )


def module_imports() -> list[tuple[str, str]]:
    """``(importing module, imported module)`` for every ``lolgps_torch`` import in the
    package, lazy ones inside functions included (a package's ``__init__`` is the package)."""
    edges: set[tuple[str, str]] = set()
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        source = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            edges.update(
                (source, n) for n in names if n.startswith("lolgps_torch.") and n != source
            )
    return sorted(edges)
