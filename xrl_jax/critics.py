"""Critic ensembles of SAC, discrete SAC, XSAC and XDSAC (docs/algorithms.md §4.5).

Conventions as in :mod:`xrl_jax.extractors`; the ensemble axis (``n_critics``) leads every output.
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from xrl_jax import sets
from xrl_jax.extractors import MLP, Observation

Array = jax.Array


def broadcast_features(features: Array, action: Array) -> Array:
    """Insert singleton axes after the batch axes of ``features`` so it broadcasts against ``action``.

    features (..., F) and action (..., k..., A) → features (..., 1..., F) (§4.5 broadcasting).
    """
    extra = action.ndim - features.ndim
    if extra < 0 or features.shape[:-1] != action.shape[: features.ndim - 1]:
        raise ValueError(
            f"action {action.shape} must start with the feature batch axes {features.shape[:-1]} "
            "(extra action axes, e.g. a K axis, may follow them)"
        )
    return features.reshape(features.shape[:-1] + (1,) * extra + features.shape[-1:])


class FeatureActionDense(nn.Module):
    """Dense on ``[F(s), a]`` with the F(s) half computed once per state.

    Same parameters as ``nn.Dense`` on the concatenation (kernel (F + A, width), bias). Splitting the
    matmul means evaluating K actions per state costs K·A·width instead of K·(F + A)·width multiplies
    for the first layer: the feature part is never tiled. With a ``plan`` (:mod:`xrl_jax.sets`) the
    actions are packed rows (P, A) and each takes its own state's part.
    """

    features: int

    @nn.compact
    def __call__(self, state_features: Array, action: Array, plan: sets.PresentRows | None = None) -> Array:
        num_features = state_features.shape[-1]
        dtype = jnp.result_type(state_features, action)
        kernel = self.param(
            "kernel",
            nn.initializers.lecun_normal(),
            (num_features + action.shape[-1], self.features),
            jnp.float32,
        ).astype(dtype)
        bias = self.param("bias", nn.initializers.zeros, (self.features,), jnp.float32).astype(dtype)
        per_state = state_features @ kernel[:num_features] + bias
        if plan is not None:
            return sets.broadcast_to_rows(per_state, plan) + action @ kernel[num_features:]
        return broadcast_features(per_state, action) + action @ kernel[num_features:]


class ContinuousQHead(nn.Module):
    """One continuous critic head C(F(s), a): Dense(width) + ReLU per width, then Dense(1)."""

    widths: Sequence[int]

    @nn.compact
    def __call__(self, state_features: Array, action: Array, plan: sets.PresentRows | None = None) -> Array:
        h = nn.relu(FeatureActionDense(self.widths[0], name="dense_0")(state_features, action, plan))
        for i, width in enumerate(self.widths[1:], start=1):
            h = nn.relu(nn.Dense(width, name=f"dense_{i}")(h))
        return nn.Dense(1, name="q")(h)[..., 0]


def critic_ensemble(head: type[nn.Module], n_critics: int) -> type[nn.Module]:
    """``n_critics`` independently initialised copies of ``head``, parameters stacked on axis 0,
    all fed the same inputs; outputs get a leading critic axis."""
    return nn.vmap(
        head,
        variable_axes={"params": 0},
        split_rngs={"params": True},
        in_axes=None,
        out_axes=0,
        axis_size=n_critics,
    )


def _q_dense(mdl: ContinuousCritic, state_features: Array, action: Array) -> Array:
    return mdl.heads(state_features, action)


def _q_packed(mdl: ContinuousCritic, plan: sets.PresentRows, state_features: Array, action: Array) -> Array:
    q = mdl.heads(state_features, sets.pack(action, plan), plan)  # (n_critics, P)
    return jnp.moveaxis(sets.unpack(q.T, plan), -1, 0)


class ContinuousCritic(nn.Module):
    """SAC / XSAC critic ensemble (§2.1, §4.5): one shared extractor F, ``n_critics`` heads.

    ``__call__(obs, action)`` → (n_critics, *action.shape[:-1]). ``action`` may carry extra axes after
    the observation batch axes (e.g. (B, K, A) for all mixture components): F(s) is computed once and
    only the head runs per action. ``features`` / ``q_from_features`` expose the two stages. Given
    ``present`` (B, K) for such component actions, the values of the others do not matter: with
    ``packing`` the heads skip them (their values are 0), otherwise they are computed as any other.
    """

    extractor: nn.Module
    widths: Sequence[int] = (256, 256)
    n_critics: int = 2
    packing: sets.Packing | None = None

    def setup(self):
        if not self.widths:
            raise ValueError("critic widths must not be empty")
        self.heads = critic_ensemble(ContinuousQHead, self.n_critics)(tuple(self.widths), name="heads")

    def features(self, obs: Observation) -> Array:
        return self.extractor(obs)

    def q_from_features(self, state_features: Array, action: Array, present: Array | None = None) -> Array:
        if present is None:
            return self.heads(state_features, action)
        if present.shape != action.shape[:-1] or present.ndim != state_features.ndim:
            raise ValueError(
                f"present {present.shape} must be the component actions' {action.shape[:-1]}, one axis "
                f"after the features' batch axes {state_features.shape[:-1]}"
            )
        plan = sets.plan_for(present, self.packing)
        return sets.packed_or_dense(self, plan, _q_packed, _q_dense, state_features, action)

    def __call__(self, obs: Observation, action: Array, present: Array | None = None) -> Array:
        return self.q_from_features(self.features(obs), action, present)


class DiscreteQHead(nn.Module):
    """One discrete critic head: MLP then duelling ``V + Adv - mean_a Adv`` or a plain N-unit layer."""

    widths: Sequence[int]
    num_actions: int
    duelling: bool = True

    @nn.compact
    def __call__(self, state_features: Array) -> Array:
        h = MLP(self.widths, name="mlp")(state_features)
        if not self.duelling:
            return nn.Dense(self.num_actions, name="q")(h)
        advantage = nn.Dense(self.num_actions, name="advantage")(h)
        value = nn.Dense(1, name="value")(h)
        return value + advantage - jnp.mean(advantage, axis=-1, keepdims=True)


class DiscreteCritic(nn.Module):
    """DSAC / XDSAC critic ensemble (§2.2, §4.5): all action values, (n_critics, ..., N)."""

    extractor: nn.Module
    num_actions: int = 12
    widths: Sequence[int] = (256, 256)
    n_critics: int = 2
    duelling: bool = True

    def setup(self):
        ensemble = critic_ensemble(DiscreteQHead, self.n_critics)
        self.heads = ensemble(tuple(self.widths), self.num_actions, self.duelling, name="heads")

    def features(self, obs: Observation) -> Array:
        return self.extractor(obs)

    def q_from_features(self, state_features: Array) -> Array:
        return self.heads(state_features)

    def __call__(self, obs: Observation) -> Array:
        return self.q_from_features(self.features(obs))


class ValueNetwork(nn.Module):
    """V(s) of the on-policy agents (:mod:`xrl_jax.ppo`): the state features of an extractor (the
    critic's Deep Set or positional encoding), an MLP, one output."""

    extractor: nn.Module
    widths: tuple[int, ...]

    @nn.compact
    def __call__(self, obs: Observation) -> Array:
        features = MLP(self.widths, name="trunk")(self.extractor(obs))
        return nn.Dense(1, name="value")(features)[..., 0]


__all__ = [
    "ContinuousCritic",
    "ContinuousQHead",
    "DiscreteCritic",
    "DiscreteQHead",
    "FeatureActionDense",
    "ValueNetwork",
    "broadcast_features",
    "critic_ensemble",
]
