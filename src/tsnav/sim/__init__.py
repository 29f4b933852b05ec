"""The simulator of tsnav: batched simulator over offline scenes, shortest paths, episodes, Gymnasium env.

Importing this package registers the Gymnasium env ids (see :mod:`tsnav.sim.gym_env`, whose docstring holds the
version history, and :mod:`tsnav.tsrm.envs`): ``tsnav/ObjectNav-v1`` (:data:`ENV_ID`, today's observations) and
``tsnav/ObjectNav-v0`` (:data:`ENV_ID_V0`, the first release's observation layout); ``gym.make("tsnav.sim:" +
ENV_ID, ...)`` imports it by itself.
"""

#: The Gymnasium id of the env (the one definition; :mod:`tsnav.sim.gym_env` re-exports it).
ENV_ID = "tsnav/ObjectNav-v1"
#: The first release's id: the same env with the ``legacy`` observation layout (``obs_layout="legacy"``).
ENV_ID_V0 = "tsnav/ObjectNav-v0"


def _register() -> None:
    try:
        import gymnasium
    except ImportError:  # the simulator itself does not need Gymnasium
        return
    # the factories add the paper's reward (tsnav.tsrm, a higher layer: named here, imported on make)
    for env_id, kwargs in ((ENV_ID, {}), (ENV_ID_V0, {"obs_layout": "legacy"})):
        if env_id not in gymnasium.registry:
            gymnasium.register(
                id=env_id,
                entry_point="tsnav.tsrm.envs:make_objectnav",
                vector_entry_point="tsnav.tsrm.envs:make_objectnav_vector",
                disable_env_checker=False,
                kwargs=kwargs,
            )


_register()
