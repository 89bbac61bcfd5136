"""A user's env (:func:`xrl_jax.custom_envs.register_env`): one agent per env, episodes restarted by
the env's own reset, evaluated on fixed episodes of that reset (:mod:`xrl_jax.evaluation.resets`); its
explanation figure draws the observed objects by weight (:mod:`xrl_jax.explain.set_figure`)."""

from __future__ import annotations

import envs
from xrl_jax.config import TrainConfig
from xrl_jax.evaluation import make_evaluate_resets
from xrl_jax.train.kinds.base import ScenarioKind


class UserEnv(ScenarioKind):
    name = "user_env"
    figure = "set"

    def make_envs(self, cfg: TrainConfig):
        """The env's own params for both (its evaluation episodes start from fixed reset keys)."""
        env, params = envs.make(cfg.env_name)
        return env, params, params

    def make_evaluate(self, cfg: TrainConfig, env, eval_params, agent):
        steps = cfg.scenario.max_episode_steps
        return make_evaluate_resets(env, eval_params, agent, cfg.eval_episodes, steps, cfg.eval_track_seed)


KIND = UserEnv()
