"""The agent of tsnav (paper III-D): observations from cached features and detections, the IOM target
memory, and the LSTM actor-critic."""

from .memory import MemoryState, TargetMemoryAggregator, relative_pose
from .model import NO_ACTION, PRESETS, ActorCritic, AgentConfig, AgentState, agent_config
from .observe import AgentObs, DetectionTable, Observer, load_bank_features, roi_pool

__all__ = [
    "ActorCritic",
    "AgentConfig",
    "AgentObs",
    "AgentState",
    "DetectionTable",
    "MemoryState",
    "NO_ACTION",
    "Observer",
    "PRESETS",
    "TargetMemoryAggregator",
    "agent_config",
    "load_bank_features",
    "relative_pose",
    "roi_pool",
]
