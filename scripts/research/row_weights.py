"""Where the S-step's weight goes: the share of its loss each part of the rollout carries.

    python scripts/research/row_weights.py RUN [RUN ...] [--width 10]

The S-step regresses the policy's mean on every row of D_g with that row's teacher precision
``Q = P_cur + lambda P_pre`` (paper eq. 8), in the net's output units. A row's pull on the fit
grows with ``tr Q``: where the teachers are surest, the loss is largest for the same error.
Per run (its replay.h5, every condition) this prints, per window of ``--width`` control steps:

- ``trace``: the median ``tr Q`` of the window's rows;
- ``eq. 8``: the window's share of ``sum_m tr Q_m`` over all rows, its share of the loss as the
  paper weights it;
- ``balanced``: the same share with each row weighted by ``w_m = mean_k tr Q_k / tr Q_m``
  (``PolicyConfig.balance_rows``): each window's share of the rows.

Where the speed cost holds the first steps back, eq. 8 puts most of the weight on the first
10 steps, and little on steps 10-30, where the peg must be aligned over the hole. Whether the
balance helps is measured by refitting the same D_g both ways:
``scripts/research/redistill.py --run RUN [--no-balance-rows]``.
"""

from __future__ import annotations

import argparse

import torch

from lolgps_torch.cli import run
from lolgps_torch.errors import LolgpsError
from lolgps_torch.lolgps.run import load_run
from lolgps_torch.policy import GaussianPolicy, PolicyConfig
from lolgps_torch.policy.sstep import _loop_rows, set_statistics


def window_table(path: str, width: int) -> list[tuple[float, float, float]]:
    """``(median tr Q, share under eq. 8, share balanced)`` per window of ``width`` steps."""
    loaded = load_run(path)
    batch = loaded.replay.load()
    T = loaded.records[0].samples.x.shape[1]
    config = PolicyConfig(pre_weight=loaded.info.stream.policy.pre_weight)
    policy = GaussianPolicy(batch.x.shape[-1], batch.mean_cur.shape[-1], config)
    set_statistics(policy, batch, config.pre_weight)
    shares = []
    for balance in (False, True):
        rows = _loop_rows(policy, batch, config.pre_weight, torch.float64, balance)
        _, _, Q = rows.unpack(torch.arange(batch.M), policy.dX, policy.dU)
        shares.append(Q.diagonal(dim1=-2, dim2=-1).sum(-1))
    step = torch.arange(batch.M) % T
    table = []
    for start in range(0, T, width):
        rows_in = (step >= start) & (step < start + width)
        table.append(
            (
                float(shares[0][rows_in].median()),
                float(shares[0][rows_in].sum() / shares[0].sum()),
                float(shares[1][rows_in].sum() / shares[1].sum()),
            )
        )
    return table


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("runs", nargs="+", help="run folders (config.json, replay.h5)")
    parser.add_argument("--width", type=int, default=10, help="steps per window (%(default)s)")
    args = parser.parse_args()
    if args.width < 1:
        raise LolgpsError(f"--width must be positive, got {args.width}")
    for path in args.runs:
        table = window_table(path, args.width)
        starts = [f"{args.width * i:>6d}" for i in range(len(table))]
        print(path)
        print("  step from " + "".join(starts))
        print("  trace     " + "".join(f"{t:6.0f}" for t, _, _ in table))
        print("  eq. 8     " + "".join(f"{s:6.2f}" for _, s, _ in table))
        print("  balanced  " + "".join(f"{b:6.2f}" for _, _, b in table))


if __name__ == "__main__":
    run(main)
