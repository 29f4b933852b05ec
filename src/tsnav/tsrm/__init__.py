"""Two-Stage Reward Mechanism (paper section III-B) and the rest of the training reward (III-D).

* :mod:`.area` - the observable trapezoid, the searched region ``RG_t`` (shapely reference and the batched
  packed-bit raster), the exploration reward's area.
* :mod:`.distance` - pose-graph distance fields ``d(p, g)`` of the distance reward.
* :mod:`.reward` - :class:`RewardConfig`, :class:`TSRMReward` (the ``RewardFn`` of :mod:`tsnav.sim.batch`)
  and :class:`TSRMRewardReference` (one episode, written from the paper).
* :mod:`.plot` - a top-down picture of one episode: stages, searched region, target.
"""

from .area import AreaConfig, AreaIndex, BatchCoverage, ExactSearchedRegion, trapezoid
from .distance import bank_pose_distance, pose_distance_fields, scene_pose_distance
from .reward import VARIANTS, RewardConfig, TSRMReward, TSRMRewardReference

__all__ = [
    "AreaConfig", "AreaIndex", "BatchCoverage", "ExactSearchedRegion", "trapezoid", "bank_pose_distance",
    "pose_distance_fields", "scene_pose_distance", "VARIANTS", "RewardConfig", "TSRMReward", "TSRMRewardReference",
]
