"""Two-Stage Reward Mechanism (paper section III-B) and the rest of the training reward (III-D).

* :mod:`.area` - the observable trapezoid, the searched region ``RG_t`` (shapely reference and the batched
  packed-bit raster), the exploration reward's area.
* :mod:`.distance` - pose-graph distance fields ``d(p, g)`` of the distance reward.
* :mod:`.terms` - the reward terms as objects (:class:`RewardTerm`: each term's batched, scalar and reference
  code), the variants as lists of term names, :func:`register_term` / :func:`register_variant`.
* :mod:`.reward` - :class:`RewardConfig`, :class:`TSRMReward` (the ``RewardFn`` of :mod:`tsnav.sim.batch`)
  and :class:`TSRMRewardReference` (one episode, written from the paper): a variant's terms, summed.
* :mod:`.plot` - a top-down picture of one episode: stages, searched region, target.
"""

from .area import AreaConfig, AreaIndex, BatchCoverage, ExactSearchedRegion, trapezoid
from .distance import bank_pose_distance, pose_distance_fields, scene_pose_distance
from .reward import VARIANTS, RewardConfig, TSRMReward, TSRMRewardReference
from .terms import TERMS, VARIANT_TERMS, RewardTerm, register_term, register_variant

__all__ = [
    "AreaConfig",
    "AreaIndex",
    "BatchCoverage",
    "ExactSearchedRegion",
    "trapezoid",
    "bank_pose_distance",
    "pose_distance_fields",
    "scene_pose_distance",
    "VARIANTS",
    "RewardConfig",
    "TSRMReward",
    "TSRMRewardReference",
    "TERMS",
    "VARIANT_TERMS",
    "RewardTerm",
    "register_term",
    "register_variant",
]
