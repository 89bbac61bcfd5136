"""xrl-jax: explainable reinforcement learning with dynamic mixture policies, in JAX.

The mixture weight a policy gives each observed object *is* its explanation: the action
distribution is exactly the weighted sum of per-object ("myopic") distributions.
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
