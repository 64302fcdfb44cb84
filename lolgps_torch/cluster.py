"""Ray, where the package uses it (the sweep's cells, the evaluation's rollouts): importing it
with an install hint, and a connection to a cluster or a local instance for a block."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from types import ModuleType
from typing import Any

from lolgps_torch.errors import LolgpsError

INSTALL_HINT = "Ray is not installed: pip install -e '.[ray]'"


def import_ray() -> ModuleType:
    """The ``ray`` module; raise :class:`LolgpsError` with the install command without it."""
    try:
        import ray
    except ImportError:
        raise LolgpsError(INSTALL_HINT) from None
    return ray


@contextlib.contextmanager
def ray_connection(ray: ModuleType, address: str | None, num_cpus: int) -> Iterator[int]:
    """Connect to Ray for the block and yield its CPU count: join the cluster at ``address``,
    or start a local instance with ``num_cpus`` CPUs; an instance already connected is used
    as it is (and left running).

    :param ray: the ray module
    :param address: a cluster address (e.g. ``auto``), or None for a local instance
    :param num_cpus: CPUs of a local instance
    """
    started = not ray.is_initialized()
    if started:
        options: dict[str, Any] = {"logging_level": logging.ERROR}
        if address is None:
            options.update(num_cpus=num_cpus, include_dashboard=False)
        try:
            ray.init(address=address, **options)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            where = f"the Ray cluster at {address}" if address else "a local Ray instance"
            raise LolgpsError(
                f"cannot start {where}: {str(exc).strip().splitlines()[-1]}"
            ) from None
    try:
        yield max(1, int(ray.cluster_resources().get("CPU", 1)))
    finally:
        if started:
            ray.shutdown()
