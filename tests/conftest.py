"""Fixtures shared across test modules."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SMALL = [
    "--max-iterations",
    "7",
    "--success-phases",
    "1",
    "--distill-steps",
    "200",
    "--repairs",
    "0",
]
CONDITIONS = [[0.0, 0.0], [0.01, -0.01]]


def ci_stream_command(tmp: Path, out: Path) -> list[str]:
    """The CI-sized stream (two conditions, small limits) into ``out``."""
    conditions = tmp / "conditions.json"
    conditions.write_text(json.dumps(CONDITIONS))
    script = str(ROOT / "scripts" / "run_stream.py")
    urdf = str(ROOT / "robots" / "kuka_peg.urdf")
    return [sys.executable, script, "--urdf", urdf, "--conditions", str(conditions), *SMALL,
            "--out", str(out)]  # fmt: skip


@pytest.fixture(scope="package")
def ci_stream(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One uninterrupted run of the CI-sized stream for the whole suite: ``<tmp>/run``."""
    tmp = tmp_path_factory.mktemp("stream")
    proc = subprocess.run(
        ci_stream_command(tmp, tmp / "run"), capture_output=True, text=True, timeout=900
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return tmp
