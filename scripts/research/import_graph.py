"""Print the import graph between lolgps_torch's packages, layer by layer, in Graphviz dot
(pipe it into ``dot -Tsvg``) or as a plain list.

    python scripts/research/import_graph.py [--dot]
"""

from __future__ import annotations

import argparse

from lolgps_torch.cli import run
from lolgps_torch.layers import LAYERS, imports, rank


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--dot", action="store_true", help="Graphviz dot instead of a list")
    args = parser.parse_args()
    edges = imports()
    if not args.dot:
        for index, units in enumerate(LAYERS):
            print(f"layer {index}: {', '.join(units)}")
        for source, target in edges:
            print(f"  {source} -> {target}")
        return
    print("digraph lolgps_torch {\n  rankdir=BT;")
    for index, units in enumerate(LAYERS):
        print(f"  {{ rank=same; {'; '.join(units)}; }}  // layer {index}")
    for source, target in edges:
        style = "" if rank(source) > rank(target) else " [color=red]"
        print(f"  {source} -> {target}{style};")
    print("}")


if __name__ == "__main__":
    run(main)
