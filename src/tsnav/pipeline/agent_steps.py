"""The steps of ``tsnav release make`` (:mod:`tsnav.pipeline.agent_recipe`), in order: torch-free, so that
``tsnav release``'s parser names them without importing the steps themselves (a saved table prints in a second)."""

#: The steps of :func:`~tsnav.pipeline.agent_recipe.make_agent`, then packing and the two evaluations
#: (:mod:`tsnav.pipeline.release`).
STEPS = ("world", "detections", "features", "train", "select", "pack", "eval")
