"""Global-policy checkpoints: a folder with ``policy.pt`` (the state dict, saved with
``torch.save``) and ``policy.json`` (dX, dU, the :class:`PolicyConfig` and the SHA-256 of
``policy.pt``), each written atomically. A run keeps one per condition in
:meth:`RunFolder.checkpoint_dir`."""

from __future__ import annotations

import hashlib
import io
import pickle
from pathlib import Path
from typing import Any

import torch

from lolgps_torch.data.run_folder import atomic_write, read_json, write_json
from lolgps_torch.errors import LolgpsError
from lolgps_torch.policy.net import GaussianPolicy

WEIGHTS_FILE = "policy.pt"
DESCRIPTION_FILE = "policy.json"


def save_policy(directory: str | Path, policy: GaussianPolicy) -> None:
    """Write ``policy`` into ``directory`` (created if missing): weights first, then the
    description with their SHA-256, each atomically. The weights are serialised in memory
    and written as bytes, so a full disk is an OSError (a :class:`LolgpsError` naming the
    file) rather than an error inside the zip writer."""
    directory = Path(directory)
    state = {name: tensor.detach().cpu() for name, tensor in policy.state_dict().items()}
    buffer = io.BytesIO()
    torch.save(state, buffer)
    data = buffer.getvalue()
    atomic_write(directory / WEIGHTS_FILE, lambda tmp: tmp.write_bytes(data))
    description = {**policy.description(), "weights_sha256": hashlib.sha256(data).hexdigest()}
    write_json(directory / DESCRIPTION_FILE, description)


def _read_weights(path: Path, sha256: Any) -> dict[str, Any]:
    """The state dict in ``path``, checked against ``sha256`` when the description has one
    (checkpoints written before it was stored have none)."""
    try:
        data = path.read_bytes()
    except OSError as error:
        raise LolgpsError(f"cannot read {path}: {error.strerror or error}") from None
    if sha256 is not None and hashlib.sha256(data).hexdigest() != sha256:
        raise LolgpsError(f"corrupt {path}: its SHA-256 differs from the one in policy.json")
    try:
        state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except (RuntimeError, pickle.UnpicklingError, EOFError, ValueError) as error:
        text = str(error).strip()
        raise LolgpsError(
            f"corrupt {path}: {text.splitlines()[0] if text else type(error).__name__}"
        ) from None
    if not isinstance(state, dict):
        raise LolgpsError(f"corrupt {path}: not a state dict")
    return state


def load_policy(directory: str | Path, device: torch.device | str = "cpu") -> GaussianPolicy:
    """The policy saved by :func:`save_policy` in ``directory`` (weights loaded with
    ``weights_only=True``); a missing or corrupt checkpoint is a :class:`LolgpsError` that
    names the file."""
    directory = Path(directory)
    try:
        description = read_json(directory / DESCRIPTION_FILE)
        if not isinstance(description, dict):
            raise LolgpsError(f"corrupt {directory / DESCRIPTION_FILE}: not a JSON object")
        state = _read_weights(directory / WEIGHTS_FILE, description.get("weights_sha256"))
        return GaussianPolicy.from_state(description, state, device)
    except LolgpsError as error:
        raise LolgpsError(f"cannot load policy from {directory}: {error}") from None
