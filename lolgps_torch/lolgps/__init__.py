"""The LOLGPS loop (paper Algorithm 2) and its baselines: per-condition local learning, the
S-step with replay, the stream, and batch GPS."""

from lolgps_torch.lolgps.methods import METHODS, Method, make_learner, method_config
from lolgps_torch.lolgps.stream import StreamConfig, StreamLearner

__all__ = ["METHODS", "Method", "StreamConfig", "StreamLearner", "make_learner", "method_config"]
