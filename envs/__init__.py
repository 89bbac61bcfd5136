"""Pure-JAX re-implementation of the CarEnv driving simulator (jittable, vmappable).

This package never imports ``xrl_jax``: dependencies point one way (experiments -> xrl_jax -> envs).
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
