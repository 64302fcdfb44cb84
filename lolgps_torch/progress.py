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
