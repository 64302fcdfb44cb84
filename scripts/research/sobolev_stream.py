"""``scripts/run_stream.py`` with the S-step's Sobolev term set (``PolicyConfig.sobolev``).

    python scripts/research/sobolev_stream.py --sobolev W [--sobolev-rows R] [run_stream flags]

Every other flag is run_stream's; the run folder's config.json records the setting.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from dataclasses import replace
from pathlib import Path

from lolgps_torch.cli import run
from lolgps_torch.lolgps import StreamConfig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, add_help=False)
    policy = StreamConfig().policy
    parser.add_argument("--sobolev", type=float, required=True)
    parser.add_argument("--sobolev-rows", type=int, default=policy.sobolev_rows)
    args, rest = parser.parse_known_args()
    path = Path(__file__).resolve().parents[1] / "run_stream.py"
    spec = importlib.util.spec_from_file_location("run_stream", path)
    if spec is None or spec.loader is None:
        raise RuntimeError(f"cannot load {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules["run_stream"] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    names = vars(module)
    flags = names["STREAM_FLAGS"]
    setting = replace(flags.default.policy, sobolev=args.sobolev, sobolev_rows=args.sobolev_rows)
    names["STREAM_FLAGS"] = replace(flags, default=replace(flags.default, policy=setting))
    sys.argv = [str(path), *rest]
    names["main"]()


if __name__ == "__main__":
    run(main)
