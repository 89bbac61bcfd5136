"""Pure loss functions of SAC, discrete SAC, XSAC and XDSAC (docs/algorithms.md §1–§3), and of PPO
and its mixture policy XPPO (generalised advantage estimation, the clipped surrogate, the clipped
value loss, the mixture's log-ratio; the last section).

Everything here works on arrays that the networks already produced, so each equation can be
checked in closed form on tiny hand-made inputs. The agents (``agents.py``) wire networks to
these functions and take the gradients. Shape conventions:

* ``q``: critic outputs stacked on a leading critic axis, ``(n_critics, B)`` for a continuous
  critic, ``(n_critics, B, N)`` for a discrete one, ``(n_critics, B, K)`` for the XSAC critic
  evaluated on all K component actions.
* ``discount``: per-transition bootstrap factor γ·(1 − terminated) (or γ·mask in general): the
  caller decides which transitions bootstrap, so terminated and truncated stay separate.
* ``weight``: optional per-transition loss weight (1 = use, 0 = ignore), e.g. to drop truncated
  transitions that were stored anyway.

All functions return ``(loss, metrics)`` where metrics is a flat dict of scalars, or plain arrays
for the helpers.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from xrl_jax.distributions import CategoricalMixture, SquashedGaussianMixture, clipped_entropy

# ------------------------------------------------------------------------------------------------
# Elementary pieces
# ------------------------------------------------------------------------------------------------


def huber(error: jax.Array, delta: float = 1.0) -> jax.Array:
    """Elementwise Huber: 0.5·e² for |e| < δ, δ·(|e| − 0.5·δ) beyond (δ = 1 in the reference)."""
    abs_error = jnp.abs(error)
    quadratic = 0.5 * jnp.square(error)
    linear = delta * (abs_error - 0.5 * delta)
    return jnp.where(abs_error < delta, quadratic, linear)


def squared(error: jax.Array) -> jax.Array:
    """Elementwise 0.5·e²: textbook SAC's critic objective; equals Huber inside |e| < 1."""
    return 0.5 * jnp.square(error)


REGRESSION_LOSSES = {"huber": huber, "l2": squared}


def weighted_mean(values: jax.Array, weight: jax.Array | None) -> jax.Array:
    """Mean over the last axis, optionally weighted; an all-zero weight gives 0 (not NaN)."""
    if weight is None:
        return jnp.mean(values, axis=-1)
    weight = jnp.broadcast_to(weight, values.shape).astype(values.dtype)
    return jnp.sum(values * weight, axis=-1) / jnp.maximum(jnp.sum(weight, axis=-1), 1.0)


# ------------------------------------------------------------------------------------------------
# TD targets (§1.2); constants for the critic step
# ------------------------------------------------------------------------------------------------


def continuous_td_target(
    reward: jax.Array,
    discount: jax.Array,
    next_q: jax.Array,
    next_log_prob: jax.Array,
    alpha: jax.Array,
) -> jax.Array:
    """y = r + γ(1−d)·(min_j Q'_j(s', a') − α·log π(a'|s')), with a' ~ π(·|s') (one sample).

    `next_q` (n_critics, B) from the target critics; the result is stop-gradiented.
    """
    soft_value = jnp.min(next_q, axis=0) - alpha * next_log_prob
    return jax.lax.stop_gradient(reward + discount * soft_value)


def discrete_td_target(
    reward: jax.Array,
    discount: jax.Array,
    next_q: jax.Array,
    next_probs: jax.Array,
    alpha: jax.Array,
) -> jax.Array:
    """y = r + γ(1−d)·(Σ_a π(a|s')·min_j Q'_j(s', a) + α·H(π(·|s'))).

    The minimum over critics is taken per action **before** the expectation (§1.2).
    `next_q` (n_critics, B, N), `next_probs` (B, N).
    """
    min_q = jnp.min(next_q, axis=0)
    soft_value = jnp.sum(next_probs * min_q, axis=-1) + alpha * clipped_entropy(next_probs)
    return jax.lax.stop_gradient(reward + discount * soft_value)


# ------------------------------------------------------------------------------------------------
# Critic loss (§1.1)
# ------------------------------------------------------------------------------------------------


def critic_loss(
    q: jax.Array,
    target: jax.Array,
    kind: str = "huber",
    weight: jax.Array | None = None,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Mean over critics of the (weighted) batch mean of Huber / L2 (Q_j − y).

    `q` (n_critics, B) holds the online critics at the *taken* actions; `target` (B,) is constant.
    For the reference's two critics this equals both its continuous form ½·Σ_j mean_b and its
    discrete form mean over the (2, B) stack.
    """
    if kind not in REGRESSION_LOSSES:
        raise ValueError(f"unknown critic loss {kind!r}; valid: {', '.join(REGRESSION_LOSSES)}")
    error = q - jax.lax.stop_gradient(target)[None]
    per_critic = weighted_mean(REGRESSION_LOSSES[kind](error), weight)
    loss = jnp.mean(per_critic)
    return loss, {"loss_critic": loss}


# ------------------------------------------------------------------------------------------------
# Actor losses (§2)
# ------------------------------------------------------------------------------------------------


def sac_actor_loss(
    log_prob: jax.Array, q: jax.Array, alpha: jax.Array
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """SAC: mean_b(α·log π(ã|s) − min_j Q_j(s, ã)), one reparameterised sample per state.

    `log_prob` (B,), `q` (n_critics, B) from the **updated** online critics; α is a constant.
    """
    alpha = jax.lax.stop_gradient(alpha)
    loss = jnp.mean(alpha * log_prob - jnp.min(q, axis=0))
    entropy = -jax.lax.stop_gradient(log_prob)
    return loss, {
        "loss_actor": loss,
        "entropy": entropy,  # per-sample, consumed by the α loss
        "entropy_mean": jnp.mean(entropy),
    }


def dsac_actor_loss(
    probs: jax.Array, q: jax.Array, alpha: jax.Array
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Discrete SAC: −mean_b(Σ_a π(a|s)·Q̄(s, a) + α·H(π(·|s))), Q̄ = **mean** over critics.

    Deviation from SAC-Discrete kept on purpose (§7.2.2): the reference actor uses the critics'
    mean, not their minimum (the target still uses the minimum).
    """
    alpha = jax.lax.stop_gradient(alpha)
    mean_q = jnp.mean(q, axis=0)
    entropy = clipped_entropy(probs)
    loss = -jnp.mean(jnp.sum(probs * mean_q, axis=-1) + alpha * entropy)
    entropy = jax.lax.stop_gradient(entropy)
    return loss, {
        "loss_actor": loss,
        "entropy": entropy,
        "entropy_mean": jnp.mean(entropy),
        "entropy_std": jnp.std(entropy),
    }


def xsac_actor_loss(
    weights: jax.Array,
    log_prob: jax.Array,
    q: jax.Array,
    alpha: jax.Array,
    kappa: jax.Array,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """XSAC, paper eq. 8 + eq. 10: mean_b[Σ_k w_k·(α·log π(a_k|s) − min_j Q_j(s, a_k)) − κ·H(w)].

    * `weights` (B, K): flattened component weights w_k (absent slots exactly 0); they keep their
      gradient (§7.2.1): through the expectation here, and inside `log_prob`, which the caller
      must evaluate under the **full mixture** for every component's own sample a_k.
    * `log_prob` (B, K): log π(a_k|s) with a_k = tanh(μ_k + σ_k ε_k), one noise per component.
    * `q` (n_critics, B, K): updated online critics at every a_k; min over critics per component.
    * κ > 0 rewards spread-out weights (the term is *subtracted*, §7.2.3).

    Absent components carry weight 0, so their (finite) values drop out; a NaN there would not,
    which is why the caller must keep them finite.
    """
    alpha = jax.lax.stop_gradient(alpha)
    kappa = jax.lax.stop_gradient(kappa)
    per_component = alpha * log_prob - jnp.min(q, axis=0)
    mixture_entropy = clipped_entropy(weights)
    loss = jnp.mean(jnp.sum(weights * per_component, axis=-1) - kappa * mixture_entropy)
    # For the α loss and the logs: the weight-averaged component log-prob Σ_k w_k log π(a_k|s).
    mean_log_prob = jax.lax.stop_gradient(jnp.sum(weights * log_prob, axis=-1))
    return loss, {
        "loss_actor": loss,
        "entropy": -mean_log_prob,
        "entropy_mean": -jnp.mean(mean_log_prob),
        "entropy_std": jnp.std(mean_log_prob),
        "mixture_entropy": jnp.mean(jax.lax.stop_gradient(mixture_entropy)),
        "kappa": kappa,
    }


def xdsac_actor_loss(
    probs: jax.Array,
    weights: jax.Array,
    q: jax.Array,
    alpha: jax.Array,
    kappa: jax.Array,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """XDSAC, paper eq. 4 + eq. 10 in closed form: −mean_b(Σ_a π(a|s)·Q̄ + α·H(π) + κ·H(w)).

    `probs` (B, N): the **mixture** π(a|s) = Σ_o w_o q_o(a) (H is the mixture's entropy, not the
    components'); `weights` (B, O); `q` (n_critics, B, N), averaged over critics as in DSAC.
    """
    kappa = jax.lax.stop_gradient(kappa)
    dsac_loss, aux = dsac_actor_loss(probs, q, alpha)
    mixture_entropy = clipped_entropy(weights)
    loss = dsac_loss - kappa * jnp.mean(mixture_entropy)
    return loss, {
        **aux,
        "loss_actor": loss,
        "mixture_entropy": jnp.mean(jax.lax.stop_gradient(mixture_entropy)),
        "kappa": kappa,
    }


# ------------------------------------------------------------------------------------------------
# Entropy coefficient (§1.3) and Polyak (§1.4)
# ------------------------------------------------------------------------------------------------


def entropy_coef_loss(
    log_alpha: jax.Array, entropy: jax.Array, target_entropy: jax.Array
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """L(log α) = log α · mean_b(Ĥ − H_target), the bracket constant.

    Ĥ is the per-sample entropy estimate from the actor step: −log π(ã|s) (SAC), −Σ_k w_k log π(a_k|s)
    (XSAC), H(π(·|s)) (discrete). This is the reference's −ℓ·mean(log π + H_target) resp.
    −ℓ·mean(H_target − H) written once: entropy above target ⇒ positive gradient ⇒ log α decreases.
    """
    gap = jax.lax.stop_gradient(jnp.mean(entropy) - target_entropy)
    loss = log_alpha * gap
    return loss, {"loss_ent_coef": loss}


def polyak_update(target_params, online_params, tau: jax.Array):
    """θ' ← (1 − τ)·θ' + τ·θ for every leaf (τ = 0.005 in every config)."""
    return jax.tree_util.tree_map(lambda t, o: (1.0 - tau) * t + tau * o, target_params, online_params)


# ------------------------------------------------------------------------------------------------
# PPO and XPPO (on-policy): advantages, the clipped surrogate, the value loss, the mixture's ratio
# ------------------------------------------------------------------------------------------------


def gae(
    rewards: jax.Array,
    values: jax.Array,
    next_values: jax.Array,
    terminated: jax.Array,
    truncated: jax.Array,
    gamma: float | jax.Array,
    lam: float | jax.Array,
) -> tuple[jax.Array, jax.Array]:
    """Generalised advantage estimation over a time-major rollout (T, ...): returns (advantages,
    value targets = advantages + values).

    δ_t = r_t + γ·(1 − terminated_t)·V'_t − V_t and A_t = δ_t + γλ·(1 − done_t)·A_{t+1}, done_t =
    terminated_t or truncated_t. ``next_values`` V'_t is the value of step t's own next observation,
    the episode's last one where it ended (not the reset observation an auto-reset env returns
    after it): so a truncated step bootstraps from where the car was, a terminated one from
    nothing, and neither passes advantages across the episode boundary. The last step's A_{T+1} is 0:
    V'_T bootstraps what the rollout did not see.
    """
    not_terminated = 1.0 - terminated.astype(rewards.dtype)
    continues = not_terminated * (1.0 - truncated.astype(rewards.dtype))
    deltas = rewards + gamma * not_terminated * next_values - values

    def backwards(later_advantage, step):
        delta, carry_on = step
        advantage = delta + gamma * lam * carry_on * later_advantage
        return advantage, advantage

    _, advantages = jax.lax.scan(backwards, jnp.zeros_like(deltas[0]), (deltas, continues), reverse=True)
    return advantages, advantages + values


def normalize_advantages(advantages: jax.Array, weight: jax.Array | None = None) -> jax.Array:
    """(A − mean) / (std + 1e-8) over the minibatch (its used entries where ``weight`` is given),
    PPO's usual per-minibatch normalisation. A constant minibatch gives zeros, not NaN."""
    weight = jnp.ones_like(advantages) if weight is None else weight.astype(advantages.dtype)
    count = jnp.maximum(jnp.sum(weight), 1.0)
    mean = jnp.sum(weight * advantages) / count
    std = jnp.sqrt(jnp.sum(weight * jnp.square(advantages - mean)) / count)
    return (advantages - mean) / (std + 1e-8)


def mixture_log_ratio(policy, sample: jax.Array, old_log_prob: jax.Array) -> jax.Array:
    """log π_new(a|s) − log π_old(a|s) of a stored rollout sample under the current policy: the
    importance ratio's log, exact for both mixtures. ``sample`` is the action index for a
    :class:`CategoricalMixture` (its log π is a logsumexp over objects), the pre-squash point u for a
    :class:`SquashedGaussianMixture` (its density at u; the tanh Jacobian is equal in both terms and
    cancels, which atanh of a saturated action could not guarantee). A one-object mixture is PPO's
    plain policy."""
    if isinstance(policy, CategoricalMixture):
        return policy.log_prob(sample) - old_log_prob
    if isinstance(policy, SquashedGaussianMixture):
        return policy.log_prob_pre_squash(sample) - old_log_prob
    kind = type(policy).__name__
    raise TypeError(f"mixture_log_ratio takes a CategoricalMixture or SquashedGaussianMixture, got {kind}")


def ppo_policy_loss(
    log_ratio: jax.Array,
    advantages: jax.Array,
    clip_eps: float | jax.Array,
    weight: jax.Array | None = None,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """PPO's clipped surrogate, −mean[min(ρ·A, clip(ρ, 1 − ε, 1 + ε)·A)], ρ = exp(log_ratio), with
    the share of clipped samples and the approximate KL(old‖new) = mean[(ρ − 1) − log ρ] (≥ 0)."""
    ratio = jnp.exp(log_ratio)
    unclipped = ratio * advantages
    clipped = jnp.clip(ratio, 1.0 - clip_eps, 1.0 + clip_eps) * advantages
    loss = -weighted_mean(jnp.minimum(unclipped, clipped), weight)
    clipped_share = weighted_mean((jnp.abs(ratio - 1.0) > clip_eps).astype(ratio.dtype), weight)
    approx_kl = weighted_mean((ratio - 1.0) - log_ratio, weight)
    stop = jax.lax.stop_gradient
    return loss, {"loss_policy": loss, "clip_fraction": stop(clipped_share), "approx_kl": stop(approx_kl)}


def ppo_value_loss(
    values: jax.Array,
    old_values: jax.Array,
    targets: jax.Array,
    clip_eps: float | jax.Array | None = None,
    weight: jax.Array | None = None,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """0.5·mean[(V − target)²], or with ``clip_eps`` PPO's clipped form 0.5·mean[max((V − target)²,
    (V_old + clip(V − V_old, −ε, ε) − target)²)]: the value moves at most ε from the rollout's."""
    error = jnp.square(values - targets)
    if clip_eps is not None:
        moved = old_values + jnp.clip(values - old_values, -clip_eps, clip_eps)
        error = jnp.maximum(error, jnp.square(moved - targets))
    loss = 0.5 * weighted_mean(error, weight)
    return loss, {"loss_value": loss}


def xppo_actor_loss(
    log_ratio: jax.Array,
    advantages: jax.Array,
    entropy: jax.Array,
    weights: jax.Array,
    clip_eps: float | jax.Array,
    entropy_coef: float | jax.Array,
    kappa: float | jax.Array,
    weight: jax.Array | None = None,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """XPPO's actor objective: the clipped surrogate − c_H·mean H(π) − κ·mean H(w), the mixture
    entropy regulariser of eq. 10 on the object weights ``weights`` (..., O). ``entropy`` is the
    policy's entropy per sample (closed form for the categorical mixture, its
    :meth:`~xrl_jax.distributions.SquashedGaussianMixture.entropy_estimate` for the Gaussian one).
    PPO is the one-object case, where H(w) = 0."""
    surrogate, metrics = ppo_policy_loss(log_ratio, advantages, clip_eps, weight)
    weights_entropy = clipped_entropy(weights)
    mean_entropy = weighted_mean(entropy, weight)
    mean_weights_entropy = weighted_mean(weights_entropy, weight)
    loss = surrogate - entropy_coef * mean_entropy - kappa * mean_weights_entropy
    stop = jax.lax.stop_gradient
    return loss, {**metrics, "loss_actor": loss, "entropy_mean": stop(mean_entropy),
                  "mixture_entropy": stop(mean_weights_entropy)}  # fmt: skip
