"""Helpers for the network tests: networks at test sizes, and the policy that the distributions build
from an actor's raw output."""

import jax.numpy as jnp
import numpy as np

import envs
from xrl_jax import networks
from xrl_jax.config import DISCRETE_ALGOS, preset
from xrl_jax.distributions import CategoricalMixture, SquashedGaussianMixture


def action_size(algo: str) -> int:
    """The action size of ``algo``'s agents, the same in every scenario (12 discrete actions, 3
    continuous action dimensions)."""
    return envs.action_size(
        envs.action_space("country_road_discrete" if algo in DISCRETE_ALGOS else "country_road")
    )


def make_test_networks(env: str, algo: str, **overrides) -> networks.Networks:
    """The paper networks of (env, algo) with AgentConfig fields overridden (e.g. tiny widths)."""
    config = preset("paper", env, algo).replace(**overrides)
    return networks.make_networks(config, networks.ENV_OBSERVATIONS[env], action_size(algo))


def mixture_policy(out) -> SquashedGaussianMixture | CategoricalMixture:
    """The policy of a mixture actor's raw output (default log σ bounds), as the agents build it."""
    if isinstance(out, networks.GaussianMixtureOutput):
        return SquashedGaussianMixture.from_objects(out.means, out.log_stds, out.mixture_logits, out.present)
    return CategoricalMixture.create(out.logits, out.mixture_logits, out.present)


def object_weights(out):
    """Object weights w_o (..., O) of a mixture actor's raw output (absent objects 0)."""
    weights = mixture_policy(out).weights
    if isinstance(out, networks.GaussianMixtureOutput):  # w_{o,c} = w_o / C, flattened object-major
        return jnp.sum(weights.reshape(out.means.shape[:-1]), axis=-1)
    return weights


def component_weights(out):
    """w_{o,c} = w_o / C (within-object weights are uniform, docs/algorithms.md §3.1.5): (..., O, C)
    for XSAC outputs."""
    return mixture_policy(out).weights.reshape(out.means.shape[:-1])


def float64_object_weights(out) -> np.ndarray:
    """w_o computed independently of the distributions, in float64 numpy: a softmax of a mixture actor's
    raw mixture logits over the present objects (absent objects 0)."""
    logits = np.where(out.present, np.asarray(out.mixture_logits, np.float64), -np.inf)
    weights = np.exp(logits - logits.max(-1, keepdims=True))
    return weights / weights.sum(-1, keepdims=True)


def trajectory_to_set(trajectory):
    """Sequence → set conversion (docs/algorithms.md §4.2): flat (..., 2L) points → rows
    ``[1, index_i, x_i, y_i]``, the layout of the Tracking observation."""
    trajectory = jnp.asarray(trajectory)
    if trajectory.shape[-1] % 2:
        raise ValueError(f"flat trajectory must have an even last axis (x, y pairs), got {trajectory.shape}")
    length = trajectory.shape[-1] // 2
    points = trajectory.reshape((*trajectory.shape[:-1], length, 2))
    index = networks.tracking_index_feature(length).astype(points.dtype)
    batch = points.shape[:-1]
    return jnp.concatenate(
        [jnp.ones((*batch, 1), points.dtype), jnp.broadcast_to(index[:, None], (*batch, 1)), points],
        axis=-1,
    )
