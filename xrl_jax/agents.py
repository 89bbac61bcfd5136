"""SAC, discrete SAC and their explainable mixture variants XSAC / XDSAC as pure-function agents.

An :class:`Agent` is a small frozen object (static: config, networks, sizes) with four pure
methods, all jittable and vmappable over a leading seed axis of the state:

* ``init(key, obs_example=None) -> AgentState``
* ``act(key, state, obs, mode="train") -> action`` (``mode``, static: one of
  ``ACT_MODES``)
* ``update(key, state, batch) -> (state, metrics)``: one train step in the order of docs/algorithms.md §1.5
* ``policy(actor_params, obs)``: the action distribution (a ``distributions`` mixture), i.e. the
  explanation for the X agents.

Batch layout expected by ``update`` (one leading batch axis B; the buffer produces it; multi-agent
transitions, e.g. the intersection's (E, 8) per-slot ones, are flattened into B — every row is one
agent's own observation, parameters are shared)::

    {
      "obs":        {"state": (B, S), "<name>_set": (B, O, F_obj)},   # float
      "action":     (B, A) float in [-1, 1] (SAC, XSAC) or (B,) int (DSAC, XDSAC),
      "reward":     (B,) float,
      "next_obs":   same structure as "obs",
      "terminated": (B,) bool or float (1 = true terminal: no bootstrap),
      "truncated":  (B,) bool or float (time limit etc.),
    }

Terminated and truncated stay separate. The bootstrap mask is 1 − terminated. With
``config.truncation == "drop"`` (default, the paper's choice) truncated transitions get weight 0
in the critic loss; the trainer normally does not store them at all (§5.3), in which case this
changes nothing. With ``"bootstrap"`` they are kept and bootstrapped (needs the true final
``next_obs``, not an auto-reset observation).

Traced hyper-parameters (learning rates, γ, τ, κ, target entropy) live in ``AgentState.hparams``
so that a sweep can vmap over them; network sizes and switches are static (the config). With
``config.lr_decay_updates`` > 0 each update scales the three learning rates by the fraction of the
decay still ahead (from ``AgentState.step``), so a resumed run keeps the same schedule.

Deviations from textbook SAC that the reference makes and this module follows (§7.2):
Huber critic loss; discrete actor on the *mean* of the critics, discrete target on the
per-action *minimum*; XSAC actor samples every component and evaluates each sample under the
full mixture; κ·H(w) subtracted; α learned on log α with Adam at the critic lr from α₀ = 0.1,
using the actor step's pre-update log-probs; the update order critic → actor (new critic) → α →
Polyak; ε = 5 % random actions for the discrete agents at training time; XSAC evaluated
stochastically, XDSAC greedily. Each is marked ``§7.2.n`` where it happens: here, in
:mod:`xrl_jax.action_spaces` or in :mod:`xrl_jax.policies`.

The agent itself tells only continuous from discrete actions (``Agent.action_space``, from
:mod:`xrl_jax.action_spaces`: random actions, ε-exploration, the TD target and the critics' values);
everything a mixture adds comes with the policy that the networks build next to their actor
(``networks.policy``, :mod:`xrl_jax.policies`: the distribution, greedy and sampled actions, the actor loss).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import optax

from xrl_jax import losses
from xrl_jax.action_spaces import ContinuousActions, DiscreteActions
from xrl_jax.agent_state import AgentState, HyperParams, adam, adam_step, make_hparams
from xrl_jax.config import AgentConfig
from xrl_jax.distributions import CategoricalMixture, SquashedGaussianMixture
from xrl_jax.networks import Networks, ObservationShape, find_set_key, make_networks, set_packing

Array = jax.Array
EVAL_MODES = ("eval", "deterministic", "stochastic")  # an evaluation acts in one of these: no ε
ACT_MODES = ("train", *EVAL_MODES)
BATCH_KEYS = ("obs", "action", "reward", "next_obs", "terminated", "truncated")


def check_eval_mode(mode: str) -> None:
    """Raise ValueError unless ``mode`` is one of :data:`EVAL_MODES`: an evaluation is refused when it
    is built, not later inside a trace."""
    if mode not in EVAL_MODES:
        raise ValueError(f"an evaluation acts in one of the modes {', '.join(EVAL_MODES)}, not {mode!r}")


def observation_shape(obs_example: Mapping[str, Any]) -> ObservationShape:
    """Read the fixed layout of one *unbatched* observation {"state": (S,), "<x>_set": (O, F)}."""
    set_key = find_set_key(obs_example)
    objects, state = obs_example[set_key], obs_example["state"]
    if len(objects.shape) != 2 or len(state.shape) != 1:
        raise ValueError(
            f"obs_example must be one unbatched observation: set (O, F) and state (S,), "
            f"got {tuple(objects.shape)} and {tuple(state.shape)}"
        )
    return ObservationShape(set_key, int(objects.shape[0]), int(objects.shape[1]), int(state.shape[0]))


def _as_float_mask(x: Array) -> Array:
    return jnp.asarray(x).astype(jnp.result_type(float))


class PolicyActing:
    """What every agent that acts through ``networks``' actor and policy offers, off-policy (SAC family)
    or on-policy (:mod:`xrl_jax.ppo`): its names, the policy as a mixture distribution, raw actor
    outputs and random actions. Needs ``config``, ``networks`` and ``action_space``."""

    @property
    def algo(self) -> str:
        return self.config.algo

    @property
    def is_discrete(self) -> bool:
        return self.config.is_discrete

    @property
    def neutral_object(self) -> bool:
        """Whether the X actor prepends the neutral object (then explanation index 0 is the state)."""
        return self.config.neutral_object

    @property
    def num_mixture_objects(self) -> int:
        """Objects in the policy's mixture: O (+1 with the neutral object) for X agents, 1 otherwise.

        ``policy(...).weights`` has ``num_mixture_objects * components_per_object`` entries for X agents.
        """
        return self.networks.num_mixture_objects

    def dummy_observation(self, batch_shape: tuple[int, ...] = ()) -> dict[str, Array]:
        return self.networks.dummy_observation(batch_shape)

    def checked_obs_example(self, obs_example: Mapping[str, Array] | None) -> Mapping[str, Array]:
        """``obs_example`` (default zeros of the agent's layout), refused if its layout differs."""
        if obs_example is None:
            return self.dummy_observation()
        if observation_shape(obs_example) != self.obs_shape:
            raise ValueError(
                f"obs_example layout {observation_shape(obs_example)} differs from the agent's "
                f"{self.obs_shape}"
            )
        return obs_example

    def policy(
        self, actor_params: Any, obs: Mapping[str, Array]
    ) -> SquashedGaussianMixture | CategoricalMixture:
        """π(·|s) as a mixture distribution (batch axes of `obs` preserved).

        SAC: a one-component squashed Gaussian; DSAC: a one-component categorical mixture;
        XSAC / XDSAC: the per-object mixtures whose ``weights`` are the explanation.
        """
        return self.policy_from_output(self.networks.actor.apply(actor_params, obs))

    def policy_from_output(self, out: Any) -> SquashedGaussianMixture | CategoricalMixture:
        """The distribution of :meth:`policy` from an already computed actor output."""
        return self.networks.policy.distribution(out)

    def actor_output(self, actor_params: Any, obs: Mapping[str, Array]) -> Any:
        """Raw actor outputs (``networks`` dataclasses: not masked, log σ not clipped), for explanations."""
        return self.networks.actor.apply(actor_params, obs)

    def random_action(self, key: Array, batch_shape: tuple[int, ...] = ()) -> Array:
        """Uniform random action (warm-up, ε-exploration)."""
        return self.action_space.random(key, batch_shape)


@dataclasses.dataclass(frozen=True, eq=False)
class Agent(PolicyActing):
    """One of SAC / DSAC / XSAC / XDSAC. Build with :func:`make_agent`; all methods are pure."""

    config: AgentConfig
    networks: Networks
    obs_shape: ObservationShape
    action_size: int  # A (continuous) or N (discrete)
    action_space: ContinuousActions | DiscreteActions = dataclasses.field(init=False, repr=False)

    def __post_init__(self) -> None:
        # The one place where the agent tells the algorithms apart: continuous or discrete actions.
        # What a mixture adds comes with the policy of its actor (``networks.policy``).
        cfg = self.config
        if cfg.is_discrete:
            space = DiscreteActions(self.action_size, cfg.resolved_epsilon_random())
        else:
            space = ContinuousActions(self.action_size)
        object.__setattr__(self, "action_space", space)

    # ---- static helpers ---------------------------------------------------------------------
    @property
    def _actor_tx(self) -> optax.GradientTransformation:
        # Reference (§1.4): with clip_norm set, SAC clips only the critic; DSAC/XSAC/XDSAC clip actor and
        # critic; α is never clipped. The intersection SAC preset sets clip_norm=None: no clipping at all.
        return adam(self.config.clip_norm if self.networks.policy.clips_actor_grads else None)

    @property
    def _critic_tx(self) -> optax.GradientTransformation:
        return adam(self.config.clip_norm)

    @property
    def _alpha_tx(self) -> optax.GradientTransformation:
        return adam(None)

    # ---- init -------------------------------------------------------------------------------
    def init(
        self, key: Array, obs_example: Mapping[str, Array] | None = None, hparams: HyperParams | None = None
    ) -> AgentState:
        """Fresh parameters, optimiser states, log α = log α₀ and step 0.

        `obs_example` (one unbatched observation; default zeros of the agent's layout) only fixes
        shapes. Actor and critic use independent keys (the reference's shared-key quirk for
        DSAC/X agents is not reproduced, §2.2). `hparams` overrides the config's traced values.
        """
        obs_example = self.checked_obs_example(obs_example)
        actor_key, critic_key = jax.random.split(key)
        actor_params = self.networks.actor.init(actor_key, obs_example)
        critic_inputs = self.action_space.critic_inputs(obs_example, self.networks.dummy_action())
        critic_params = self.networks.critic.init(critic_key, *critic_inputs)
        if hparams is None:
            hparams = make_hparams(self.config, self.action_size)
        log_alpha = jnp.asarray(hparams.init_log_alpha)
        return AgentState(
            actor_params=actor_params,
            critic_params=critic_params,
            target_critic_params=jax.tree_util.tree_map(jnp.array, critic_params),
            log_alpha=log_alpha,
            actor_opt_state=self._actor_tx.init(actor_params),
            critic_opt_state=self._critic_tx.init(critic_params),
            alpha_opt_state=self._alpha_tx.init(log_alpha),
            step=jnp.zeros((), jnp.int32),
            hparams=hparams,
        )

    def act(self, key: Array, state: AgentState, obs: Mapping[str, Array], mode: str = "train") -> Array:
        """An action for `obs` (any leading batch axes).

        * "train": stochastic; XSAC / XDSAC use the fast path (sample the object, then run only its
          head, §3.7); discrete agents take a uniform random action with probability ε = 0.05
          (§7.2.9, `config.epsilon_random`).
        * "eval": the reference's evaluation policy (§3.8): SAC tanh(μ), DSAC argmax, XSAC
          **stochastic** fast sample (§7.2.5), XDSAC argmax of the mixture probabilities.
        * "deterministic": greedy for every agent (XSAC: the approximate mode of §3.9, not what
          the paper's numbers used).
        * "stochastic": a sample of the policy for every agent, without ε (a diagnostic: shows how
          much of a greedy agent's evaluation hangs on near-ties between actions).
        """
        if mode not in ACT_MODES:
            raise ValueError(f"unknown act mode {mode!r}; valid modes: {', '.join(ACT_MODES)}")
        params, policy = state.actor_params, self.networks.policy
        sample_key, explore_key, coin_key = jax.random.split(key, 3)
        if mode == "deterministic" or (mode == "eval" and not policy.stochastic_eval):
            return policy.greedy(self.networks.actor.apply(params, obs))
        action = policy.sample(self.networks.actor, params, obs, sample_key)
        return self.action_space.explore(action, mode, explore_key, coin_key)

    # ---- losses (params + state + batch + key -> (loss, aux)) -------------------------------
    def critic_loss(
        self, critic_params: Any, state: AgentState, batch: Mapping[str, Any], key: Array
    ) -> tuple[Array, dict[str, Array]]:
        """Critic loss with the TD target of §1.2 computed from `state` (pre-update actor, target
        critics, pre-update α); only `critic_params` is differentiated."""
        hp = state.hparams
        alpha = jax.lax.stop_gradient(state.alpha)
        reward = jnp.asarray(batch["reward"])
        terminated = _as_float_mask(batch["terminated"])
        truncated = _as_float_mask(batch["truncated"])
        discount = hp.gamma * (1.0 - terminated)  # §7.2.8: done = terminated only
        weight = 1.0 - truncated if self.config.truncation == "drop" else None
        next_pi = self.policy(state.actor_params, batch["next_obs"])
        critic, actions = self.networks.critic, self.action_space
        target = actions.td_target(
            critic, state.target_critic_params, batch["next_obs"], next_pi, reward, discount, alpha, key
        )
        q = actions.taken_q(critic, critic_params, batch["obs"], batch["action"])
        loss, aux = losses.critic_loss(q, target, self.config.critic_loss, weight)
        aux = {**aux, "q_val_min": jnp.min(target), "q_val_max": jnp.max(target)}
        return loss, aux

    def actor_loss(
        self, actor_params: Any, state: AgentState, batch: Mapping[str, Any], key: Array
    ) -> tuple[Array, dict[str, Array]]:
        """Actor loss with the critics in `state` (the **updated** online critics in `update`,
        §7.2.7) and the pre-update α; only `actor_params` is differentiated."""
        alpha = state.alpha
        obs = batch["obs"]
        critic_params = jax.lax.stop_gradient(state.critic_params)
        critic = functools.partial(self.networks.critic.apply, critic_params, obs)  # critic(*action_args)
        out = self.networks.actor.apply(actor_params, obs)
        return self.networks.policy.actor_loss(out, critic, alpha, state.hparams.kappa, key)

    # ---- one train step ---------------------------------------------------------------------
    def update(
        self, key: Array, state: AgentState, batch: Mapping[str, Any]
    ) -> tuple[AgentState, dict[str, Array]]:
        """One gradient step in the order of §1.5 (§7.2.7):

        1. TD target with the pre-update actor, target critics and pre-update α;
        2. critic Adam step; 3. actor Adam step against the **updated** critic, pre-update α;
        4. α Adam step from step 3's entropy estimates (auto-α only); 5. Polyak from the new critic.
        """
        self.check_batch(batch)
        hp = _scheduled_hparams(self.config, state)
        target_key, actor_key = jax.random.split(key)

        (critic_loss, critic_aux), critic_grads = jax.value_and_grad(self.critic_loss, has_aux=True)(
            state.critic_params, state, batch, target_key
        )
        critic_params, critic_opt_state = adam_step(
            self._critic_tx, critic_grads, state.critic_opt_state, state.critic_params, hp.critic_lr
        )
        state_new_critic = state.replace(critic_params=critic_params)

        (actor_loss, actor_aux), actor_grads = jax.value_and_grad(self.actor_loss, has_aux=True)(
            state.actor_params, state_new_critic, batch, actor_key
        )
        actor_params, actor_opt_state = adam_step(
            self._actor_tx, actor_grads, state.actor_opt_state, state.actor_params, hp.actor_lr
        )

        metrics: dict[str, Array] = {}
        log_alpha, alpha_opt_state = state.log_alpha, state.alpha_opt_state
        if self.config.auto_alpha:
            # §7.2.6: log α, Adam at the critic lr, entropies from the pre-update actor (step 3).
            (alpha_loss, _), alpha_grad = jax.value_and_grad(losses.entropy_coef_loss, has_aux=True)(
                state.log_alpha, actor_aux["entropy"], hp.target_entropy
            )
            log_alpha, alpha_opt_state = adam_step(
                self._alpha_tx, alpha_grad, state.alpha_opt_state, state.log_alpha, hp.alpha_lr
            )
            metrics["loss_ent_coef"] = alpha_loss

        target_critic_params = losses.polyak_update(state.target_critic_params, critic_params, hp.tau)

        new_state = state.replace(
            actor_params=actor_params,
            critic_params=critic_params,
            target_critic_params=target_critic_params,
            log_alpha=log_alpha,
            actor_opt_state=actor_opt_state,
            critic_opt_state=critic_opt_state,
            alpha_opt_state=alpha_opt_state,
            step=state.step + 1,
        )
        metrics.update({k: v for k, v in critic_aux.items()})
        metrics.update({k: v for k, v in actor_aux.items() if k != "entropy"})
        metrics["loss_critic"] = critic_loss
        metrics["loss_actor"] = actor_loss
        metrics["grad_norm_critic"] = optax.tree.norm(critic_grads)
        metrics["grad_norm_actor"] = optax.tree.norm(actor_grads)
        metrics["ent_coef"] = jnp.exp(log_alpha)  # post-update α for every agent (§7.4)
        packing = set_packing(self.config)
        if packing is not None:
            metrics["packed_overflow"] = _packed_overflow(self.obs_shape.set_key, batch, packing)
        return new_state, metrics

    def check_batch(self, batch: Mapping[str, Any]) -> None:
        """Raise a clear error for a batch that does not follow the documented layout."""
        _check_batch(self, batch)


def _scheduled_hparams(config: AgentConfig, state: AgentState) -> HyperParams:
    """The hyper-parameters of this update: with ``lr_decay_updates`` > 0, the three learning
    rates fall linearly from their set values (update 0) to zero (update ``lr_decay_updates``)."""
    hp = state.hparams
    decay = config.lr_decay_updates
    if not decay:
        return hp
    scale = jnp.clip(1.0 - state.step / decay, 0.0, 1.0).astype(hp.actor_lr.dtype)
    return hp.replace(
        actor_lr=hp.actor_lr * scale, critic_lr=hp.critic_lr * scale, alpha_lr=hp.alpha_lr * scale
    )


def _packed_overflow(set_key: str, batch: Mapping[str, Any], packing) -> Array:
    """1.0 when the batch's observations or next observations hold more present objects than the
    Deep Sets' packed rows, so that their layers computed on every slot (xrl_jax.sets); else 0.
    Averaged over a chunk's updates: how often ``packed_rows`` was too small."""

    def overflows(obs):
        present = jnp.asarray(obs[set_key])[..., 0] > 0
        return jnp.sum(present) > packing.capacity(*present.shape)

    return (overflows(batch["obs"]) | overflows(batch["next_obs"])).astype(jnp.result_type(float))


def _check_batch(agent: Agent, batch: Mapping[str, Any]) -> None:
    """:meth:`Agent.check_batch`, outside the class to keep it short."""
    missing = [k for k in BATCH_KEYS if k not in batch]
    if missing:
        raise ValueError(f"batch is missing {missing}; expected keys {list(BATCH_KEYS)}")
    reward = jnp.shape(batch["reward"])
    if len(reward) != 1:
        raise ValueError(f"batch['reward'] must have shape (B,), got {reward}")
    size = reward[0]
    for name in ("terminated", "truncated"):
        if jnp.shape(batch[name]) != (size,):
            raise ValueError(f"batch[{name!r}] must have shape ({size},), got {jnp.shape(batch[name])}")
    action_shape = agent.action_space.shape((size,))
    if jnp.shape(batch["action"]) != action_shape:
        raise ValueError(
            f"batch['action'] must have shape {action_shape} for {agent.algo}, "
            f"got {jnp.shape(batch['action'])}"
        )
    expected = {
        "state": (size, agent.obs_shape.state_dim),
        agent.obs_shape.set_key: (size, agent.obs_shape.num_objects, agent.obs_shape.object_features),
    }
    for name in ("obs", "next_obs"):
        obs = batch[name]
        if set(obs) != set(expected):
            raise ValueError(f"batch[{name!r}] must have keys {sorted(expected)}, got {sorted(obs)}")
        for k, shape in expected.items():
            if jnp.shape(obs[k]) != shape:
                raise ValueError(f"batch[{name!r}][{k!r}] must have shape {shape}, got {jnp.shape(obs[k])}")


def make_agent(config: AgentConfig, obs_example: Mapping[str, Any], action_size: int) -> Agent:
    """Build an agent for observations shaped like `obs_example` (one unbatched observation) and
    `action_size` = A (continuous: SAC, XSAC) or N (discrete: DSAC, XDSAC).

    With ``config.packed_rows`` its per-object layers compute on the present objects only
    (:mod:`xrl_jax.sets`), and on every slot in a call that overflows; that fallback stays a branch
    that runs only when needed if your own ``jax.vmap`` over agent states names its axis
    ``xrl_jax.sets.MEMBERS_AXIS`` (``jax.vmap(agent.update, axis_name=MEMBERS_AXIS)``, as the
    trainer does). Under an unnamed ``vmap`` both sides run on every call: the same results, the
    dense cost."""
    if not isinstance(config, AgentConfig):
        raise TypeError(f"config must be an AgentConfig, got {type(config).__name__}")
    if not isinstance(action_size, int) or action_size < 1:
        raise ValueError(f"action_size must be a positive integer, got {action_size!r}")
    obs_shape = observation_shape(obs_example)
    networks = make_networks(config, obs_shape, action_size)
    return Agent(config=config, networks=networks, obs_shape=obs_shape, action_size=action_size)


__all__ = [
    "ACT_MODES",
    "BATCH_KEYS",
    "EVAL_MODES",
    "Agent",
    "AgentState",
    "HyperParams",
    "check_eval_mode",
    "make_agent",
    "make_hparams",
    "observation_shape",
]
