"""Global-policy checkpoints: a folder with ``policy.pt`` (the state dict, saved with
``torch.save``) and ``policy.json`` (dX, dU and the :class:`PolicyConfig`), each written
atomically. A run keeps one per condition in :meth:`RunFolder.checkpoint_dir`."""

from __future__ import annotations

import pickle
from pathlib import Path

import torch

from lolgps_torch.data.run_folder import atomic_write, read_json, write_json
from lolgps_torch.errors import LolgpsError
from lolgps_torch.policy.net import GaussianPolicy

WEIGHTS_FILE = "policy.pt"
DESCRIPTION_FILE = "policy.json"


def save_policy(directory: str | Path, policy: GaussianPolicy) -> None:
    """Write ``policy`` into ``directory`` (created if missing): weights first, then the
    description, each atomically."""
    directory = Path(directory)
    state = {name: tensor.detach().cpu() for name, tensor in policy.state_dict().items()}
    atomic_write(directory / WEIGHTS_FILE, lambda tmp: torch.save(state, tmp))
    write_json(directory / DESCRIPTION_FILE, policy.description())


def load_policy(directory: str | Path, device: torch.device | str = "cpu") -> GaussianPolicy:
    """The policy saved by :func:`save_policy` in ``directory`` (weights loaded with
    ``weights_only=True``); a missing or corrupt checkpoint is a :class:`LolgpsError`."""
    directory = Path(directory)
    try:
        description = read_json(directory / DESCRIPTION_FILE)
        state = torch.load(directory / WEIGHTS_FILE, map_location="cpu", weights_only=True)
        if not isinstance(description, dict) or not isinstance(state, dict):
            raise LolgpsError("not a policy checkpoint")
        return GaussianPolicy.from_state(description, state, device)
    except (LolgpsError, OSError, RuntimeError, pickle.UnpicklingError) as error:
        text = str(error).strip()
        reason = text.splitlines()[0] if text else type(error).__name__
        raise LolgpsError(f"cannot load policy from {directory}: {reason}") from None
