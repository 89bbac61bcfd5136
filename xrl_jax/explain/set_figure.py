"""The explanation figure of a user's env (:func:`xrl_jax.custom_envs.register_env`), which has no
bird view: one evaluation episode rolled out on the device with the policy's explanation at every
step, drawn as (left) the objects at one step, each where its ``object_xy`` features put it
relative to the agent (or, without positions, as one bar per slot), coloured and sized by its
mixture weight, and (right) every slot's weight over the whole episode. Needs matplotlib."""

from __future__ import annotations

import io
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from xrl_jax.evaluation.resets import reset_episode_keys
from xrl_jax.explain.explanations import explain


def make_set_episode_rollout(env, agent, set_key: str, max_steps: int):
    """``rollout(episode, seed, key, params, agent_state) -> dict`` of per-step arrays (leading axis
    ``max_steps``): the set (``objects``), the weights, rewards, end flags and ``valid`` (False after
    the episode ended). Episode ``episode`` of evaluation seed ``seed`` replays exactly the start and
    env randomness of the run's evaluation (:mod:`xrl_jax.evaluation.resets`); ``key`` drives the
    policy's own sampling."""

    def rollout(episode, seed, key, params, agent_state):
        reset_keys, stream_keys = reset_episode_keys(seed, episode + 1)
        obs, state = env.reset_env(reset_keys[episode], params)

        def step(carry, t):
            obs, state, done, key = carry
            key, act_key = jax.random.split(key)
            action = agent.act(act_key, agent_state, obs, "eval")
            explanation = explain(agent, agent_state, obs)
            step_key = jax.random.fold_in(stream_keys[episode], t)
            next_obs, next_state, reward, terminated, truncated, _ = env.step_env(
                step_key, state, action, params
            )
            out = {
                "objects": obs[set_key],
                "weights": explanation.weights,
                "action": action,
                "reward": reward,
                "terminated": terminated,
                "truncated": truncated,
                "valid": ~done,
            }
            freeze = lambda new, old: jax.tree.map(lambda n, o: jnp.where(done, o, n), new, old)
            ended = done | terminated | truncated
            return (freeze(next_obs, obs), freeze(next_state, state), ended, key), out

        carry = (obs, state, jnp.zeros((), bool), key)
        return jax.lax.scan(step, carry, jnp.arange(max_steps, dtype=jnp.int32))[1]

    return jax.jit(rollout, static_argnums=(0, 1))


def object_weights(record: dict[str, Any]) -> tuple[np.ndarray, int]:
    """``(weights of the O slots (T, O), index of slot 0 in the weights)``: a neutral (state-only)
    component, when the agent has one, comes first; a baseline's single pseudo-object gives None."""
    weights, objects = np.asarray(record["weights"]), np.asarray(record["objects"])
    offset = weights.shape[-1] - objects.shape[-2]
    return (weights[:, offset:] if offset >= 0 else None), offset


def set_attributions(record: dict[str, Any], threshold: float) -> list[dict]:
    """One row per valid step: action, reward and every present object with weight >= ``threshold``
    (index = its slot, weight, its features)."""
    weights, _ = object_weights(record)
    rows = []
    for t in np.flatnonzero(np.asarray(record["valid"])):
        objects = np.asarray(record["objects"][t])
        items = []
        if weights is not None:
            for slot in np.flatnonzero((objects[:, 0] > 0) & (weights[t] >= threshold)):
                items.append(
                    {
                        "index": int(slot),
                        "weight": float(weights[t, slot]),
                        "features": objects[slot].tolist(),
                    }
                )
        action = np.asarray(record["action"][t]).tolist()
        rows.append(
            {"step": int(t), "action": action, "reward": float(record["reward"][t]), "objects": items}
        )
    return rows


def draw_set_step(record: dict[str, Any], step: int, object_xy, title: str, size=(1280, 720)) -> np.ndarray:
    """The figure of step ``step`` as an RGB array (H, W, 3)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    weights, _ = object_weights(record)
    objects = np.asarray(record["objects"][step])
    present = objects[:, 0] > 0
    valid = np.asarray(record["valid"])
    fig, (scene, history) = plt.subplots(1, 2, figsize=(size[0] / 100, size[1] / 100), dpi=100)
    step_weights = weights[step] if weights is not None else np.full(len(objects), np.nan)
    if object_xy is not None:
        x, y = objects[present][:, object_xy[0]], objects[present][:, object_xy[1]]
        w = np.nan_to_num(step_weights[present])
        scene.scatter(x, y, s=60 + 1500 * w, c=w, cmap="viridis", vmin=0, vmax=1, edgecolors="k")
        for slot, xi, yi, wi in zip(np.flatnonzero(present), x, y, w, strict=True):
            scene.annotate(f"{slot}: {wi:.2f}", (xi, yi), textcoords="offset points", xytext=(8, 8))
        scene.scatter([0], [0], marker="*", s=300, c="tab:red", label="agent")
        scene.set_aspect("equal", adjustable="datalim")
        scene.set_xlabel(f"object feature {object_xy[0]} (relative x)")
        scene.set_ylabel(f"object feature {object_xy[1]} (relative y)")
        scene.legend(loc="best")
    else:
        scene.bar(np.arange(len(objects)), np.where(present, np.nan_to_num(step_weights), 0.0))
        scene.set_xlabel("object slot")
        scene.set_ylabel("mixture weight")
    scene.set_title(f"step {step}: objects by mixture weight")
    if weights is not None:
        shown = np.where(present_over_time(record) & valid[:, None], weights, np.nan).T
        image = history.imshow(shown, aspect="auto", cmap="viridis", vmin=0, vmax=1, interpolation="nearest")
        history.axvline(step, color="tab:red", lw=1)
        history.set_xlim(-0.5, max(int(valid.sum()), 1) - 0.5)
        fig.colorbar(image, ax=history, label="mixture weight (blank: empty slot)")
    else:
        history.text(0.5, 0.5, "a baseline: no per-object weights", ha="center", va="center")
    history.set_xlabel("step")
    history.set_ylabel("object slot")
    history.set_title("weights over the episode")
    fig.suptitle(title)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="raw", dpi=100)
    width, height = fig.canvas.get_width_height()
    plt.close(fig)
    return np.frombuffer(buffer.getvalue(), np.uint8).reshape(height, width, 4)[..., :3]


def present_over_time(record: dict[str, Any]) -> np.ndarray:
    return np.asarray(record["objects"])[..., 0] > 0
