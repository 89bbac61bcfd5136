"""xrl-jax: explainable reinforcement learning with dynamic mixture policies, in JAX.

The mixture weight a policy gives each observed object *is* its explanation: the action
distribution is exactly the weighted sum of per-object ("myopic") distributions.

``xrl_jax.register_env`` makes a user's own JAX env a scenario the trainer knows
(:mod:`xrl_jax.custom_envs`); it is loaded on first use, so ``import xrl_jax.config`` stays jax-free.
"""

import importlib

__version__ = "0.1.0"

_EXPORTS = {"register_env": "xrl_jax.custom_envs", "unregister_env": "xrl_jax.custom_envs"}


def __getattr__(name):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'xrl_jax' has no attribute {name!r}")


__all__ = ["__version__", "register_env", "unregister_env"]
