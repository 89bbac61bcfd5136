"""PPO and XPPO as pure-function agents: the on-policy family of the same actors and policies.

The paper closes with "our explainable policies can be applied to any RL framework with stochastic
policies"; this module applies them to PPO. Each on-policy algorithm has an off-policy twin whose
actor and policy it takes (``xrl_jax.config.ACTOR_TWIN``): PPO (continuous, SAC's squashed Gaussian),
DPPO (discrete, DSAC's categorical), XPPO (XSAC's per-object squashed-Gaussian mixture) and XDPPO
(XDSAC's per-object categorical mixture), whose mixture weights are the explanation as in the SAC
family. Beside the actor a state-value network V(s) (the critic's extractor and widths, one output).

A :class:`PPOAgent` has the SAC agents' acting surface (``init``, ``act(key, state, obs, mode)``,
``policy``, ``random_action``), so evaluation and explanations treat both families alike, and two
methods of its own:

* ``rollout_act(key, state, obs) -> (action, sample, log_prob, value)``: what a rollout stores. The
  ``sample`` is what the probability ratio is later taken at: the action index for the categorical
  policies, the pre-squash point u for the Gaussian ones (``action = tanh(u)``), so that the ratio is
  exact (``xrl_jax.losses.mixture_log_ratio``);
* ``update(key, state, batch) -> (state, metrics)``: ``ppo_epochs`` passes over the rollout's
  flattened ``batch`` (``obs``, ``sample``, ``log_prob``, ``value``, ``advantage``, ``target``; the
  advantages and value targets from :func:`xrl_jax.losses.gae`; optionally ``mask``, the steps that
  count, where agent slots sit steps out), each in ``ppo_minibatches`` shuffled
  minibatches; per minibatch one Adam step of the actor on XPPO's objective (clipped surrogate,
  entropy bonus, κ·H(w): :func:`xrl_jax.losses.xppo_actor_loss`) and one of the value network.

The entropy bonus takes the categorical mixture's exact entropy, and for the Gaussian mixture, which
has none in closed form, its unbiased estimate (one reparameterised draw per component,
``SquashedGaussianMixture.entropy_estimate``). Actor and value keep separate optimisers, so that the
value loss needs no weight against the policy's; both clip the global gradient norm at ``clip_norm``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from xrl_jax import losses
from xrl_jax.action_spaces import ContinuousActions, DiscreteActions
from xrl_jax.agent_state import adam, adam_step
from xrl_jax.agents import ACT_MODES, PolicyActing, observation_shape
from xrl_jax.config import ACTOR_TWIN, ON_POLICY_TRACED_FIELDS, AgentConfig
from xrl_jax.critics import ValueNetwork
from xrl_jax.distributions import CategoricalMixture
from xrl_jax.networks import Networks, make_extractor, make_networks, set_packing

Array = jax.Array
ROLLOUT_KEYS = ("obs", "sample", "log_prob", "value", "advantage", "target")


@struct.dataclass
class PPOHyperParams:
    """The on-policy family's traced constants (scalars, vmappable over members: a sweep's points);
    the fields are ``xrl_jax.config.ON_POLICY_TRACED_FIELDS``."""

    actor_lr: Array
    critic_lr: Array
    gamma: Array
    gae_lambda: Array
    clip_eps: Array
    ent_coef: Array
    kappa: Array


@struct.dataclass
class PPOState:
    """Everything that changes during training; a pytree with an optional leading member axis."""

    actor_params: Any
    value_params: Any
    actor_opt_state: Any
    value_opt_state: Any
    step: Array  # minibatch updates so far (the learning-rate decay counts them)
    hparams: PPOHyperParams


def make_ppo_hparams(config: AgentConfig) -> PPOHyperParams:
    def scalar(x) -> Array:
        return jnp.asarray(x, dtype=jnp.result_type(float))

    return PPOHyperParams(**{name: scalar(getattr(config, name)) for name in ON_POLICY_TRACED_FIELDS})


@dataclasses.dataclass(frozen=True, eq=False)
class PPOAgent(PolicyActing):
    """PPO / DPPO / XPPO / XDPPO. Build with :func:`make_ppo_agent`; all methods are pure."""

    config: AgentConfig
    networks: Networks  # the twin's actor and policy (its critic is not used)
    value_network: ValueNetwork
    obs_shape: Any
    action_size: int

    @property
    def action_space(self) -> ContinuousActions | DiscreteActions:
        """Random actions; PPO explores by its own policy, so without ε."""
        if self.is_discrete:
            return DiscreteActions(self.action_size, 0.0)
        return ContinuousActions(self.action_size)

    @property
    def _tx(self):
        return adam(self.config.clip_norm)

    # ---- state ----------------------------------------------------------------------------------
    def init(
        self,
        key: Array,
        obs_example: Mapping[str, Array] | None = None,
        hparams: PPOHyperParams | None = None,
    ) -> PPOState:
        obs_example = self.checked_obs_example(obs_example)
        actor_key, value_key = jax.random.split(key)
        actor_params = self.networks.actor.init(actor_key, obs_example)
        value_params = self.value_network.init(value_key, obs_example)
        return PPOState(
            actor_params=actor_params,
            value_params=value_params,
            actor_opt_state=self._tx.init(actor_params),
            value_opt_state=self._tx.init(value_params),
            step=jnp.zeros((), jnp.int32),
            hparams=make_ppo_hparams(self.config) if hparams is None else hparams,
        )

    # ---- acting ---------------------------------------------------------------------------------
    def value(self, value_params: Any, obs: Mapping[str, Array]) -> Array:
        return self.value_network.apply(value_params, obs)

    def act(self, key: Array, state: PPOState, obs: Mapping[str, Array], mode: str = "train") -> Array:
        """"train" and "stochastic": a sample of π; "deterministic": greedy; "eval": as the twin is
        evaluated (greedy, XPPO like XSAC a sample: docs/algorithms.md §7.2.5)."""
        if mode not in ACT_MODES:
            raise ValueError(f"unknown act mode {mode!r}; valid modes: {', '.join(ACT_MODES)}")
        policy = self.networks.policy
        if mode == "deterministic" or (mode == "eval" and not policy.stochastic_eval):
            return policy.greedy(self.actor_output(state.actor_params, obs))
        return self.policy(state.actor_params, obs).sample(key)

    def rollout_act(self, key: Array, state: PPOState, obs: Mapping[str, Array]):
        """``(action for the env, sample to store, its log π, V(s))`` for a rollout step."""
        pi = self.policy(state.actor_params, obs)
        if isinstance(pi, CategoricalMixture):
            sample = pi.sample(key)
            action, log_prob = sample, pi.log_prob(sample)
        else:
            sample, log_prob = pi.sample_pre_squash_and_log_prob(key)
            action = jnp.tanh(sample)
        return action, sample, log_prob, self.value(state.value_params, obs)

    # ---- learning -------------------------------------------------------------------------------
    def actor_loss(self, actor_params: Any, state: PPOState, batch: Mapping[str, Any], key: Array):
        hp = state.hparams
        pi = self.policy(actor_params, batch["obs"])
        log_ratio = losses.mixture_log_ratio(pi, batch["sample"], batch["log_prob"])
        entropy = pi.entropy() if isinstance(pi, CategoricalMixture) else pi.entropy_estimate(key)
        mask = batch.get("mask")  # the steps actors took (agent slots); None: all of them
        advantages = losses.normalize_advantages(batch["advantage"], mask)
        return losses.xppo_actor_loss(
            log_ratio, advantages, entropy, pi.weights, hp.clip_eps, hp.ent_coef, hp.kappa, mask
        )

    def value_loss(self, value_params: Any, batch: Mapping[str, Any]):
        values = self.value(value_params, batch["obs"])
        return losses.ppo_value_loss(
            values, batch["value"], batch["target"], self.config.value_clip_eps, batch.get("mask")
        )

    def _learning_rate_scale(self, step: Array) -> Array:
        """Linear decay to zero over ``lr_decay_updates`` minibatch updates (1 without decay)."""
        total = self.config.lr_decay_updates
        if not total:
            return jnp.ones((), jnp.result_type(float))
        return jnp.clip(1.0 - step / total, 0.0, 1.0).astype(jnp.result_type(float))

    def minibatch_update(self, key: Array, state: PPOState, batch: Mapping[str, Any]):
        """One Adam step of the actor and one of the value network on ``batch``."""
        scale = self._learning_rate_scale(state.step)
        (_, actor_aux), actor_grads = jax.value_and_grad(self.actor_loss, has_aux=True)(
            state.actor_params, state, batch, key
        )
        (_, value_aux), value_grads = jax.value_and_grad(self.value_loss, has_aux=True)(
            state.value_params, batch
        )
        actor_params, actor_opt = adam_step(
            self._tx, actor_grads, state.actor_opt_state, state.actor_params, state.hparams.actor_lr * scale
        )
        value_params, value_opt = adam_step(
            self._tx, value_grads, state.value_opt_state, state.value_params, state.hparams.critic_lr * scale
        )
        state = state.replace(
            actor_params=actor_params, value_params=value_params, actor_opt_state=actor_opt,
            value_opt_state=value_opt, step=state.step + 1,
        )  # fmt: skip
        return state, {**actor_aux, **value_aux}

    def update(self, key: Array, state: PPOState, batch: Mapping[str, Any]):
        """``ppo_epochs`` shuffled passes over ``batch`` (leading axis B, a multiple of
        ``ppo_minibatches``), one :meth:`minibatch_update` per minibatch; metrics are the means over
        every minibatch."""
        missing = [k for k in ROLLOUT_KEYS if k not in batch]
        if missing:
            raise ValueError(f"the rollout batch lacks {', '.join(missing)}")
        size = jax.tree.leaves(batch["advantage"])[0].shape[0]
        parts = self.config.ppo_minibatches
        if size % parts:
            raise ValueError(f"a rollout of {size} transitions cannot be split into {parts} minibatches")

        def epoch(state, key):
            order_key, *update_keys = jax.random.split(key, parts + 1)
            order = jax.random.permutation(order_key, size).reshape(parts, size // parts)
            minibatches = jax.tree.map(lambda x: x[order], batch)
            return jax.lax.scan(
                lambda s, inputs: self.minibatch_update(inputs[0], s, inputs[1]),
                state,
                (jnp.stack(update_keys), minibatches),
            )

        state, metrics = jax.lax.scan(epoch, state, jax.random.split(key, self.config.ppo_epochs))
        return state, jax.tree.map(jnp.mean, metrics)


def make_ppo_agent(config: AgentConfig, obs_example: Mapping[str, Array], action_size: int) -> PPOAgent:
    """The :class:`PPOAgent` of ``config`` (its ``algo`` one of ``xrl_jax.config.ON_POLICY_ALGOS``) for
    observations laid out as ``obs_example`` (one unbatched observation) and ``action_size`` actions
    (A continuous dimensions or N discrete actions)."""
    if not config.is_on_policy:
        raise ValueError(
            f"make_ppo_agent builds the on-policy agents; {config.algo!r} is off-policy (make_agent)"
        )
    obs_shape = observation_shape(obs_example)
    # The SAC-family twin only shapes the networks; the rollout's truncation mode is the on-policy one's.
    twin = config.replace(algo=ACTOR_TWIN[config.algo], truncation="drop")
    networks = make_networks(twin, obs_shape, action_size)
    extractor = make_extractor(config, set_packing(config))
    value_network = ValueNetwork(extractor, (config.critic_width,) * config.critic_depth)
    return PPOAgent(config, networks, value_network, obs_shape, action_size)
