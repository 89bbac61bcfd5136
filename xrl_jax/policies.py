"""The policy of each actor: how its raw output becomes an action distribution, a greedy and a sampled
action, and the actor objective of its algorithm (docs/algorithms.md §2, §3).

:func:`xrl_jax.networks.make_networks` builds one of these next to the actor it belongs to, so the
agents (:mod:`xrl_jax.agents`) only tell continuous from discrete actions: what a mixture adds (the
per-object weights, XSAC's per-component samples, the κ-weighted mixture entropy, the fast acting path
of §3.7) comes with the policy of the actor that has one.

Every policy offers the same four members:

* ``distribution(out)``: π(·|s) from the actor's raw output (masking, log σ clipping and the mixture
  weights are :mod:`xrl_jax.distributions`' job);
* ``greedy(out)``: the deterministic action;
* ``sample(actor, params, obs, key)``: a stochastic action (before the discrete agents' ε-exploration);
* ``actor_loss(out, critic, alpha, kappa, key) -> (loss, aux)``, where ``critic(*action_args)`` are
  the updated critics bound to the batch's observations (continuous: ``critic(action[, weighted])``,
  discrete: ``critic()`` for every action's value);

and two flags: ``clips_actor_grads`` (§1.4: with ``clip_norm`` set the reference clips SAC's critic
only, the other agents' actor and critic) and ``stochastic_eval`` (§7.2.5: XSAC is evaluated on a
sample, the others greedily).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, ClassVar

import flax.linen as nn
import jax
import jax.numpy as jnp

from xrl_jax import losses
from xrl_jax.actors import CategoricalMixtureOutput, GaussianMixtureOutput, GaussianOutput
from xrl_jax.distributions import CategoricalMixture, SquashedGaussianMixture, squashed_gaussian
from xrl_jax.sets import Packing

Array = jax.Array
Critic = Callable[..., Array]
Loss = tuple[Array, dict[str, Array]]


def _sample_full(policy, actor: nn.Module, params: Any, obs: Any, key: Array) -> Array:
    """A sample of the whole distribution (every head computed)."""
    return policy.distribution(actor.apply(params, obs)).sample(key)


def _sample_mixture(policy, actor: nn.Module, params: Any, obs: Any, key: Array) -> Array:
    """The fast path of §3.7 (object first, then its head alone); a uniform mixture has no φ to
    draw the object from, so it samples the whole distribution."""
    if policy.uniform_mixture:
        return _sample_full(policy, actor, params, obs, key)
    return actor.apply(params, obs, key, method=actor.sample_fast).action


@dataclasses.dataclass(frozen=True)
class SquashedGaussianPolicy:
    """SAC (§2.1): one squashed Gaussian tanh(N(μ, σ)) from a :class:`~xrl_jax.actors.GaussianOutput`."""

    log_std_min: float
    log_std_max: float
    clips_actor_grads: ClassVar[bool] = False
    stochastic_eval: ClassVar[bool] = False
    sample = _sample_full

    def distribution(self, out: GaussianOutput) -> SquashedGaussianMixture:
        return squashed_gaussian(out.mean, out.log_std, self.log_std_min, self.log_std_max)

    def greedy(self, out: GaussianOutput) -> Array:
        return jnp.tanh(out.mean)

    def actor_loss(self, out: GaussianOutput, critic: Critic, alpha: Array, kappa: Array, key: Array) -> Loss:
        action, log_prob = self.distribution(out).sample_and_log_prob(key)  # reparameterised in μ, σ
        return losses.sac_actor_loss(log_prob, critic(action), alpha)


@dataclasses.dataclass(frozen=True)
class GaussianMixturePolicy:
    """XSAC (§2.3): the per-object squashed-Gaussian mixture of a
    :class:`~xrl_jax.actors.GaussianMixtureOutput`; ``uniform_mixture`` ignores its mixture logits.
    ``component_packing`` packs the critic's rows of the K component actions (:mod:`xrl_jax.sets`)."""

    log_std_min: float
    log_std_max: float
    uniform_mixture: bool = False
    component_packing: Packing | None = None
    clips_actor_grads: ClassVar[bool] = True
    stochastic_eval: ClassVar[bool] = True
    sample = _sample_mixture

    def distribution(self, out: GaussianMixtureOutput) -> SquashedGaussianMixture:
        logits = None if self.uniform_mixture else out.mixture_logits
        bounds = dict(log_std_min=self.log_std_min, log_std_max=self.log_std_max)
        return SquashedGaussianMixture.from_objects(out.means, out.log_stds, logits, out.present, **bounds)

    def greedy(self, out: GaussianMixtureOutput) -> Array:
        return self.distribution(out).approximate_mode()  # §3.9

    def actor_loss(
        self, out: GaussianMixtureOutput, critic: Critic, alpha: Array, kappa: Array, key: Array
    ) -> Loss:
        # §7.2.1: one reparameterised sample per component, each scored under the full mixture
        # (floored density), Q = min of the updated critics, weights keep their gradient.
        pi = self.distribution(out)
        actions, log_probs = pi.sample_per_component(key, floor_density=True, packing=self.component_packing)
        q = critic(actions, pi.weighted)  # F(s) once, heads per component
        return losses.xsac_actor_loss(pi.weights, log_probs, q, alpha, kappa)


@dataclasses.dataclass(frozen=True)
class CategoricalPolicy:
    """DSAC (§2.2): a one-component categorical mixture of the actor's centred action logits (..., N)."""

    clips_actor_grads: ClassVar[bool] = True
    stochastic_eval: ClassVar[bool] = False
    sample = _sample_full

    def distribution(self, out: Array) -> CategoricalMixture:
        return CategoricalMixture.create(out[..., None, :])

    def greedy(self, out: Array) -> Array:
        return jnp.argmax(out, axis=-1).astype(jnp.int32)

    def actor_loss(self, out: Array, critic: Critic, alpha: Array, kappa: Array, key: Array) -> Loss:
        pi = self.distribution(out)
        q = critic()
        return losses.dsac_actor_loss(pi.probs(), q, alpha)  # §7.2.2: mean of critics


@dataclasses.dataclass(frozen=True)
class CategoricalMixturePolicy:
    """XDSAC (§2.4): the per-object categorical mixture of a
    :class:`~xrl_jax.actors.CategoricalMixtureOutput`; ``uniform_mixture`` ignores its mixture logits."""

    uniform_mixture: bool = False
    clips_actor_grads: ClassVar[bool] = True
    stochastic_eval: ClassVar[bool] = False
    sample = _sample_mixture

    def distribution(self, out: CategoricalMixtureOutput) -> CategoricalMixture:
        logits = None if self.uniform_mixture else out.mixture_logits
        return CategoricalMixture.create(out.logits, logits, out.present)

    def greedy(self, out: CategoricalMixtureOutput) -> Array:
        return self.distribution(out).mode().astype(jnp.int32)

    def actor_loss(
        self, out: CategoricalMixtureOutput, critic: Critic, alpha: Array, kappa: Array, key: Array
    ) -> Loss:
        """The closed-form loss plus ``mean_mixture_logits``: the mean raw mixture logit of the
        present objects, a log of how far φ drifts."""
        pi = self.distribution(out)
        q = critic()
        loss, aux = losses.xdsac_actor_loss(pi.probs(), pi.weights, q, alpha, kappa)
        present = out.present.astype(loss.dtype)
        centred = jnp.where(out.present, out.mixture_logits, 0.0)
        mean_logit = jnp.sum(centred) / jnp.maximum(jnp.sum(present), 1.0)
        aux["mean_mixture_logits"] = jax.lax.stop_gradient(mean_logit)
        return loss, aux


Policy = SquashedGaussianPolicy | GaussianMixturePolicy | CategoricalPolicy | CategoricalMixturePolicy

__all__ = [
    "CategoricalMixturePolicy",
    "CategoricalPolicy",
    "GaussianMixturePolicy",
    "Policy",
    "SquashedGaussianPolicy",
]
