"""The simulator of tsnav: batched simulator over offline scenes, shortest paths, episodes, Gymnasium env.

Importing this package registers the Gymnasium env id ``tsnav/ObjectNav-v0`` (see :mod:`tsnav.sim.gym_env`
and :mod:`tsnav.tsrm.envs`); ``gym.make("tsnav.sim:tsnav/ObjectNav-v0", ...)`` imports it by itself.
"""

ENV_ID = "tsnav/ObjectNav-v0"


def _register() -> None:
    try:
        import gymnasium
    except ImportError:  # the simulator itself does not need Gymnasium
        return
    if ENV_ID not in gymnasium.registry:
        # the factories add the paper's reward (tsnav.tsrm, a higher layer: named here, imported on make)
        gymnasium.register(id=ENV_ID, entry_point="tsnav.tsrm.envs:make_objectnav",
                           vector_entry_point="tsnav.tsrm.envs:make_objectnav_vector", disable_env_checker=False)


_register()
