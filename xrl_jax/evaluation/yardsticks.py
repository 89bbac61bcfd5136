"""The scenarios' yardsticks, scored by the agents' own evaluation: the hand controller on the racing
scenarios (docs/carenv-single-agent.md §8.3), the scripted driver on the Intersection."""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp

import envs
from envs import hand_controller
from envs.intersection_driver import DriverSettings, scripted_actions
from xrl_jax import config
from xrl_jax.evaluation.multiagent import make_evaluate_multiagent_policy
from xrl_jax.evaluation.protocol import make_evaluate_policy, summarize_episodes
from xrl_jax.tracks import cached_track_bank, racing_env


def hand_controller_evaluation(scenario: str, eval_track_seed: int, episodes: int):
    """``score(target_speed=None) -> averages``: the hand controller (:mod:`envs.hand_controller`) on a
    run's held-out tracks, ``episodes`` episodes, episode ``i`` on track ``i`` of the bank of
    ``eval_track_seed`` (the protocol of :func:`make_evaluate`), as :func:`summarize_episodes`'s
    averages. The tracks are prepared and the evaluation compiled once; the target speed is an input
    of it, so scoring several speeds costs one compilation. ``scenario`` is ``"tracking"`` or
    ``"country_road"``; the controller drives with continuous actions whichever action space the
    agents had (the tracks and rewards are the same)."""
    if config.scenario(scenario).yardstick != "hand controller":
        raise ValueError(f"the hand controller drives tracking or country_road, not {scenario!r}")
    env, eval_params = racing_env(scenario, cached_track_bank(eval_track_seed, episodes))

    def policy(key, target, obs, env_states, per_episode):
        del key, obs
        return per_episode(lambda state, p: hand_controller.centre_line_action(env, state, p, target))(
            env_states
        )

    evaluate = jax.jit(make_evaluate_policy(env, eval_params, policy, episodes))

    def score(target_speed: float | None = None) -> dict[str, Any]:
        speed = hand_controller.DEFAULT_TARGET_SPEED if target_speed is None else float(target_speed)
        if not (math.isfinite(speed) and speed > 0):
            raise ValueError(f"the target speed must be a positive number of m/s, got {target_speed}")
        episodes_out = jax.device_get(evaluate(jax.random.PRNGKey(0), jnp.asarray(speed)))
        return {"target_speed": speed, **summarize_episodes(episodes_out)}

    return score


def scripted_driver_evaluation(episodes: int):
    """``score(cruise_speed=None) -> averages``: the scripted Intersection driver
    (:mod:`envs.intersection_driver`) in every slot, scored by the agents' evaluation
    (:func:`make_evaluate_multiagent`: the same ``episodes`` episodes of 60 s with 8 vehicles), as
    :func:`summarize_episodes`'s averages plus ``target_speed`` (the cruise speed). Compiled once;
    the settings are inputs of the compiled evaluation."""
    env, params = envs.make("intersection")
    eval_params = params.replace(max_vehicles=8)

    def policy(key, settings, obs):
        del key  # the driver is deterministic
        return jax.vmap(scripted_actions, in_axes=(0, None, None))(obs, eval_params, settings)

    evaluate = jax.jit(make_evaluate_multiagent_policy(env, eval_params, policy, episodes))

    def score(cruise_speed: float | None = None, **changes) -> dict[str, Any]:
        """The averages at ``cruise_speed`` (None: the default), other DriverSettings fields changed."""
        settings = DriverSettings()._replace(**changes)
        if cruise_speed is not None:
            if not (math.isfinite(cruise_speed) and cruise_speed > 0):
                raise ValueError(f"the cruise speed must be a positive number of m/s, got {cruise_speed}")
            settings = settings._replace(cruise_speed=float(cruise_speed))
        traced = jax.tree.map(jnp.asarray, settings)
        episodes_out = jax.device_get(evaluate(jax.random.PRNGKey(0), traced))
        return {"target_speed": settings.cruise_speed, **summarize_episodes(episodes_out)}

    return score


# Each yardstick (the scenario's fact, xrl_jax.config.Scenario.yardstick) as
# (scenario, eval_track_seed, episodes) -> score.
YARDSTICKS = {
    "hand controller": hand_controller_evaluation,
    # The Intersection's evaluation episodes are fixed: no track seed.
    "scripted driver": lambda scenario, eval_track_seed, episodes: scripted_driver_evaluation(episodes),
}


def has_yardstick(scenario: str) -> bool:
    """Whether the scenario has a yardstick to score (a user's env has none)."""
    return config.scenario(scenario).yardstick in YARDSTICKS


def yardstick_evaluation(scenario: str, eval_track_seed: int, episodes: int):
    """The scenario's yardstick as ``score(speed=None)``: the hand controller on the racing
    scenarios' held-out tracks, the scripted driver on the Intersection (whose evaluation episodes
    are fixed, so ``eval_track_seed`` is not used there)."""
    yardstick = config.scenario(scenario).yardstick
    if yardstick not in YARDSTICKS:
        raise ValueError(f"{scenario} has no yardstick to score")
    return YARDSTICKS[yardstick](scenario, eval_track_seed, episodes)


def evaluate_yardstick(
    scenario: str, eval_track_seed: int, episodes: int, target_speed: float | None = None
) -> dict[str, Any]:
    """The scenario's yardstick at one speed (:func:`yardstick_evaluation`)."""
    return yardstick_evaluation(scenario, eval_track_seed, episodes)(target_speed)
