"""Progress bars for terminals only: a tqdm bar on standard error when it is a TTY, nothing
otherwise, so logs, pipes and CI output get no control characters."""

from __future__ import annotations

import sys
from collections.abc import Iterable
from typing import TypeVar

from tqdm import tqdm

Item = TypeVar("Item")


def progress(iterable: Iterable[Item], total: int | None = None, desc: str = "") -> Iterable[Item]:
    """``iterable`` wrapped in a tqdm bar on stderr when stderr is a terminal, else unchanged.

    :param iterable: what to iterate.
    :param total: its length, for iterables without ``len`` (e.g. generators).
    :param desc: the bar's label.
    """
    if not sys.stderr.isatty():
        return iterable
    return tqdm(iterable, total=total, desc=desc, leave=False, dynamic_ncols=True)


class Bar:
    """A tqdm bar on stderr with log lines printed above it on a terminal; elsewhere no bar
    and the lines printed as they are, one per event.

    :param total: steps to completion. :param desc: the bar's label.
    """

    def __init__(self, total: int, desc: str = "") -> None:
        self.bar = (
            tqdm(total=total, desc=desc, leave=False, dynamic_ncols=True)
            if sys.stderr.isatty()
            else None
        )

    def write(self, line: str) -> None:
        """One log line on standard output (above the bar)."""
        if self.bar is None:
            print(line, flush=True)
        else:
            self.bar.write(line, file=sys.stdout)

    def update(self, steps: int = 1) -> None:
        if self.bar is not None:
            self.bar.update(steps)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
