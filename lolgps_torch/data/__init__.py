"""Data on disk: the HDF5 replay of successful trajectories (ALGORITHM.md section 7)."""

from lolgps_torch.data.replay import ConditionRecord, ConditionSamples, ReplayBuffer

__all__ = ["ConditionRecord", "ConditionSamples", "ReplayBuffer"]
