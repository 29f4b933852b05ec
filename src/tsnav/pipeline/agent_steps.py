"""The steps of ``tsnav release make`` (:mod:`tsnav.pipeline.agent_recipe`), in order: torch-free, so that
``tsnav release``'s parser names them without importing the steps themselves (a saved table prints in a second)."""

#: The steps of :func:`~tsnav.pipeline.agent_recipe.make_agent`, then packing and the two evaluations
#: (:mod:`tsnav.pipeline.release`).
STEPS = ("world", "detections", "features", "train", "select", "pack", "eval")

#: How the agents of a world other than ``ithor-real`` are evaluated, written into their cards
#: (:func:`tsnav.pipeline.release.agent_card`): the split (``eval_split``) and its episodes (``episodes``). RoboTHOR has
#: no test split: its benchmark is the challenge's 1,800 val episodes on the 15 val scenes (``challenge``: converted
#: with :mod:`tsnav.sim.challenge` from the copy packaged with tsnav), so no val episode may score its checkpoints.
#: Cards without these fields are evaluated on the ``test`` split with episodes drawn as
#: :data:`tsnav.pipeline.release.SPLIT_EPISODES` says.
WORLD_EVAL = {"robothor-real": {"eval_split": "val", "episodes": "challenge"}}
