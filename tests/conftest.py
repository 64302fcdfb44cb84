"""Tests run torch on one thread, as the scripts do (see ``lolgps_torch.cli.run``)."""

import torch

torch.set_num_threads(1)
