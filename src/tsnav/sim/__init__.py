"""sim stage of tsnav: batched simulator over offline scenes, shortest paths, episodes, Gymnasium env.

Importing this package registers the Gymnasium env id ``tsnav/ObjectNav-v0`` (see :mod:`tsnav.sim.gym_env`).
"""

ENV_ID = "tsnav/ObjectNav-v0"


def _register() -> None:
    try:
        import gymnasium
    except ImportError:  # the simulator itself does not need Gymnasium
        return
    if ENV_ID not in gymnasium.registry:
        gymnasium.register(id=ENV_ID, entry_point="tsnav.sim.gym_env:ObjectNavEnv",
                           vector_entry_point="tsnav.sim.gym_env:ObjectNavVectorEnv", disable_env_checker=False)


_register()
