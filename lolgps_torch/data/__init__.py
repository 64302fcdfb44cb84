"""Data on disk: the HDF5 replay of successful trajectories (docs/ALGORITHM.md section 7), and its
export as a documented HDF5 or Minari dataset (datasets/README.md)."""

from lolgps_torch.data.dataset import ExportedTrajectories, ExportReport
from lolgps_torch.data.export_hdf5 import export_hdf5, load_dataset
from lolgps_torch.data.export_minari import export_minari
from lolgps_torch.data.replay import ConditionRecord, ReplayBuffer

__all__ = [
    "ConditionRecord",
    "ExportReport",
    "ExportedTrajectories",
    "ReplayBuffer",
    "export_hdf5",
    "export_minari",
    "load_dataset",
]
