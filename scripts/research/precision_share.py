"""Where in time the S-step's fit is weighted: the teachers' precision, step by step.

    python scripts/research/precision_share.py RUN [RUN ...] [--edges 0 10 20 40 60 100]

The S-step fits the policy to each condition's teacher at D_g's states weighted by the
teacher's precision P_cur (eq. 8, ``(mu_theta - mu_cur)^T P_cur (mu_theta - mu_cur)``), so a
step whose teacher is very sure of its action dominates the loss, and the policy is fitted
loosely where the teacher is less sure. Per run, the share of the trace of P_cur,
``tr P_cur(t)`` summed over D_g's samples, that falls in each window of steps
``[edges_k, edges_{k+1})``, averaged over the conditions.

The speed cost's curvature ``wv_j = speed_weight / v_j^2`` enters P_cur wherever a teacher
moves a joint faster than its free share: along the approach from the start pose, not during
the slow descent into the hole, which the S-step then fits less closely.
"""

from __future__ import annotations

import argparse
import itertools

import torch

from lolgps_torch.cli import run
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps.run import LoadedRun, load_run


def shares(loaded: LoadedRun, edges: list[int]) -> list[float]:
    """The mean over conditions of each window's share of ``tr P_cur`` summed over samples."""
    per_condition = []
    for record in loaded.records:
        prec = record.samples.prec_cur  # [M, T, dU, dU]
        if prec.shape[0] == 0:
            continue
        trace = prec.diagonal(dim1=-2, dim2=-1).sum(-1).sum(0)  # [T]
        windows = [trace[a:b].sum() for a, b in itertools.pairwise(edges)]
        per_condition.append(torch.stack(windows) / trace.sum())
    if not per_condition:
        raise LolgpsError("no condition has stored successful samples")
    return torch.stack(per_condition).mean(0).tolist()


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", help="run folders")
    parser.add_argument("--edges", type=int, nargs="+", default=[0, 10, 20, 40, 60, 100])
    args = parser.parse_args()
    loaded = [load_run(path) for path in args.runs]
    for path, one in zip(args.runs, loaded, strict=True):
        T = one.records[0].samples.x.shape[1]
        edges = args.edges
        if len(edges) < 2 or edges != sorted(set(edges)) or edges[0] < 0 or edges[-1] > T:
            raise LolgpsError(f"--edges must rise from 0 or more to at most {T}, got {edges}")
        pairs = zip(itertools.pairwise(edges), shares(one, edges), strict=True)
        windows = ", ".join(f"{a}-{b - 1} {share:.2f}" for (a, b), share in pairs)
        print(f"{path}: share of the teachers' precision by steps: {windows}")


if __name__ == "__main__":
    run(main)
