"""Flax (linen) networks for SAC, discrete SAC and their explainable mixture variants XSAC / XDSAC.

Reference: docs/algorithms.md §2-§4 and §7; paper §III-F and Table I.

The pieces live in three modules, all re-exported here (``from xrl_jax import networks``):
:mod:`xrl_jax.extractors` (observation helpers, MLP, Fourier features, Deep Set, positional encodings,
the feature extractors), :mod:`xrl_jax.actors` (the per-object mixture actors with their fast acting
path, and the baseline actors) and :mod:`xrl_jax.critics` (critic ensembles). This module assembles one
agent's actor and critic from an :class:`~xrl_jax.config.AgentConfig` and the observation layout.

The networks return raw outputs; masking absent objects, clipping log σ and the mixture weights belong
to :mod:`xrl_jax.distributions`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from xrl_jax.actors import (
    CategoricalActor,
    CategoricalMixtureOutput,
    FastSample,
    GaussianActor,
    GaussianMixtureOutput,
    GaussianOutput,
    MixtureCategoricalActor,
    MixtureGaussianActor,
    centre,
)
from xrl_jax.config import SCENARIOS, AgentConfig
from xrl_jax.critics import (
    ContinuousCritic,
    ContinuousQHead,
    DiscreteCritic,
    DiscreteQHead,
    FeatureActionDense,
    broadcast_features,
    critic_ensemble,
)
from xrl_jax.extractors import (
    MLP,
    STATE_KEY,
    DeepSet,
    DeepSetExtractor,
    FlatPEExtractor,
    FourierFeatures,
    find_set_key,
    float_dtype,
    object_inputs,
    positional_encoding,
    present_mask,
    tracking_index_feature,
)
from xrl_jax.policies import (
    CategoricalMixturePolicy,
    CategoricalPolicy,
    GaussianMixturePolicy,
    Policy,
    SquashedGaussianPolicy,
)
from xrl_jax.sets import Packing

Array = jax.Array


@dataclasses.dataclass(frozen=True)
class ObservationShape:
    """Fixed observation layout of one scenario (§0)."""

    set_key: str
    num_objects: int
    object_features: int
    state_dim: int


ENV_OBSERVATIONS: dict[str, ObservationShape] = {
    name: ObservationShape(facts.set_key, facts.num_objects, facts.object_features, facts.state_dim)
    for name, facts in SCENARIOS.items()
}


def dummy_observation(shape: ObservationShape, batch_shape: tuple[int, ...] = ()) -> dict[str, Array]:
    """Zero observation (no object present) with the env's fixed shapes, for initialisation."""
    dtype = float_dtype()
    return {
        STATE_KEY: jnp.zeros((*batch_shape, shape.state_dim), dtype),
        shape.set_key: jnp.zeros((*batch_shape, shape.num_objects, shape.object_features), dtype),
    }


def set_packing(config: AgentConfig) -> Packing | None:
    """How the per-object layers pack the present objects (``packed_rows`` per set), or ``None``:
    every slot (no ``packed_rows``, or ``dense_sets``)."""
    if config.packed_rows is None or config.dense_sets:
        return None
    return Packing(float(config.packed_rows))


def make_extractor(config: AgentConfig, packing: Packing | None = None) -> nn.Module:
    """The critic's (and the baseline actors') extractor named by ``config.feature_extractor``, its
    Deep Set packed by ``packing``."""
    if config.feature_extractor == "deepset":
        return DeepSetExtractor(
            width=config.fe_width,
            item_depth=config.fe_item_depth,
            set_depth=config.fe_set_depth,
            fourier_scale=config.fourier_scale,
            state_width=config.fe_width,
            packing=packing,
        )
    return FlatPEExtractor(num_freqs=config.pe_freqs)


@dataclasses.dataclass(frozen=True)
class Networks:
    """The actor and critic modules of one agent plus helpers to initialise them on dummy inputs.

    ``action_size`` is A (continuous agents) or N (discrete agents).
    """

    config: AgentConfig
    obs_shape: ObservationShape
    action_size: int
    actor: nn.Module
    critic: nn.Module
    policy: Policy  # how the actor's output becomes π(·|s), its actions and its actor loss
    component_packing: Packing | None = None  # XSAC: its K component actions (critic heads, eq. 9 pairs)

    @property
    def num_mixture_objects(self) -> int:
        """Objects of the X actors' mixture: O, plus one for the neutral object (1 for the baselines)."""
        if not self.config.is_mixture:
            return 1
        return self.obs_shape.num_objects + int(self.config.neutral_object)

    def dummy_observation(self, batch_shape: tuple[int, ...] = ()) -> dict[str, Array]:
        return dummy_observation(self.obs_shape, batch_shape)

    def dummy_action(self, batch_shape: tuple[int, ...] = ()) -> Array:
        if self.config.is_discrete:
            return jnp.zeros(batch_shape, jnp.int32)
        return jnp.zeros((*batch_shape, self.action_size), float_dtype())

    def init_actor(self, key: Array) -> Any:
        return self.actor.init(key, self.dummy_observation())

    def init_critic(self, key: Array) -> Any:
        if self.config.is_discrete:
            return self.critic.init(key, self.dummy_observation())
        return self.critic.init(key, self.dummy_observation(), self.dummy_action())


def make_networks(config: AgentConfig, obs_shape: ObservationShape, action_size: int) -> Networks:
    """Build the actor of §4.6 with its policy, and the critic (each with its own extractor where it
    has one).

    ``action_size`` is A (SAC, XSAC) or N (DSAC, XDSAC); the config is validated on construction.
    With ``config.packed_rows`` the per-object layers compute on the present objects only
    (:mod:`xrl_jax.sets`), falling back to every slot in a call that overflows. That fallback is a
    branch that runs only when needed, as long as a ``jax.vmap`` over several agents' states (members)
    names its axis :data:`xrl_jax.sets.MEMBERS_AXIS`; under any other ``vmap`` both sides run every call
    (the same result, at the dense cost).
    """
    return _networks(config, obs_shape, action_size, set_packing(config))


def packed_only(networks: Networks) -> Networks:
    """``networks`` with their packed computation compiled alone, without the fallback to every slot,
    for counting the FLOPs a packed call runs (XLA's cost analysis counts a conditional as its larger
    branch). Lower and count them, never run them: a call that overflows drops objects. The one way to
    build such networks (:class:`~xrl_jax.sets.Packing`'s ``fallback``)."""
    packing = set_packing(networks.config)
    if packing is None:
        return networks
    packing = dataclasses.replace(packing, fallback=False)
    return _networks(networks.config, networks.obs_shape, networks.action_size, packing)


def _networks(
    c: AgentConfig, obs_shape: ObservationShape, action_size: int, packing: Packing | None
) -> Networks:
    if c.is_mixture:
        actor, policy = _mixture_actor(c, obs_shape, action_size, packing)
    else:
        actor, policy = _baseline_actor(c, action_size, packing)
    # XSAC's policy has the critic score its K component actions per row, packed like the actor's rows
    component_packing = getattr(policy, "component_packing", None)
    critic_widths = (c.critic_width,) * c.critic_depth
    if c.is_discrete:
        extractor = make_extractor(c, packing)
        critic = DiscreteCritic(extractor, action_size, critic_widths, c.n_critics, c.duelling)
    else:
        critic = ContinuousCritic(make_extractor(c, packing), critic_widths, c.n_critics, component_packing)
    return Networks(c, obs_shape, action_size, actor, critic, policy, component_packing)


def _baseline_actor(c: AgentConfig, action_size: int, packing: Packing | None) -> tuple[nn.Module, Policy]:
    """SAC's or DSAC's actor (own extractor, MLP) and its policy."""
    actor_widths = (c.actor_width,) * c.actor_depth
    if c.is_discrete:
        return CategoricalActor(make_extractor(c, packing), action_size, actor_widths), CategoricalPolicy()
    actor = GaussianActor(make_extractor(c, packing), action_size, actor_widths)
    return actor, SquashedGaussianPolicy(c.resolved_log_std_min(), c.log_std_max)


def _mixture_actor(
    c: AgentConfig, obs_shape: ObservationShape, action_size: int, packing: Packing | None
) -> tuple[nn.Module, Policy]:
    """XSAC's or XDSAC's per-object actor and its policy. The actor's packed rows include the neutral
    object, always present; the XSAC critic scores C component actions per row."""
    mixture_packing = None if packing is None else packing.scaled(1.0, extra_rows=int(c.neutral_object))
    mixture = dict(
        width=c.actor_width,
        depth=c.actor_depth,
        weight_depth=c.weight_depth,
        set_key=obs_shape.set_key,
        neutral_object=c.neutral_object,
        neutral_flag=c.neutral_flag,
        uniform_mixture=c.uniform_mixture,
        packing=mixture_packing,
    )
    if c.is_discrete:
        return MixtureCategoricalActor(action_size, **mixture), CategoricalMixturePolicy(c.uniform_mixture)
    component_packing = None
    if mixture_packing is not None:
        component_packing = mixture_packing.scaled(c.components_per_object)
    log_std = dict(log_std_min=c.resolved_log_std_min(), log_std_max=c.log_std_max)
    actor = MixtureGaussianActor(
        action_size, components_per_object=c.components_per_object, **log_std, **mixture
    )
    return actor, GaussianMixturePolicy(
        **log_std, uniform_mixture=c.uniform_mixture, component_packing=component_packing
    )


__all__ = [
    "ENV_OBSERVATIONS",
    "MLP",
    "STATE_KEY",
    "CategoricalActor",
    "CategoricalMixtureOutput",
    "ContinuousCritic",
    "ContinuousQHead",
    "DeepSet",
    "DeepSetExtractor",
    "DiscreteCritic",
    "DiscreteQHead",
    "FastSample",
    "FeatureActionDense",
    "FlatPEExtractor",
    "FourierFeatures",
    "GaussianActor",
    "GaussianMixtureOutput",
    "GaussianOutput",
    "MixtureCategoricalActor",
    "MixtureGaussianActor",
    "Networks",
    "ObservationShape",
    "broadcast_features",
    "centre",
    "critic_ensemble",
    "dummy_observation",
    "find_set_key",
    "make_extractor",
    "make_networks",
    "object_inputs",
    "packed_only",
    "positional_encoding",
    "present_mask",
    "set_packing",
    "tracking_index_feature",
]
