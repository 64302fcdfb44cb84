"""PyBullet, imported without its build-time banner (printed from C on import), and
:func:`silenced`, under which what PyBullet prints from C (``b3Warning ... Bad inertia tensor
properties`` and the like while it loads a URDF) does not reach the terminal, so that a
script's output stays its own lines: the loader already says, in one line each, what PyBullet
would warn about (:mod:`lolgps_torch.robot.validate`)."""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from types import ModuleType


@contextlib.contextmanager
def silenced() -> Iterator[None]:
    """Within the block, the process's standard output and error (file descriptors 1 and 2,
    where C code writes) go to the null device; Python's own streams are flushed first."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, devnull):
            os.close(fd)


def _import_quietly() -> ModuleType:
    with silenced():
        import pybullet
    return pybullet


pb = _import_quietly()
