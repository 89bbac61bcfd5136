"""The scenario kinds, one object each (:class:`~xrl_jax.train.kinds.base.ScenarioKind`): racing on
tracks, the multi-agent Intersection, a user's env. A scenario names its kind
(:attr:`xrl_jax.config.Scenario.kind`); the trainer, the evaluation, the report, the explanation
figures and the campaign ask that object how such runs build their envs, restart episodes, store
transitions and update, what a chunk and the rollout window report, how they are evaluated and what
they cost, instead of branching on the kind.

A new kind is one module here (a :class:`ScenarioKind` subclass and its ``KIND``) and one line of
:data:`KINDS` (docs/layout.md shows one).
"""

from __future__ import annotations

from xrl_jax.config import TrainConfig, scenario
from xrl_jax.train.kinds import multi_agent, racing, user_env
from xrl_jax.train.kinds.base import ScenarioKind

KINDS: dict[str, ScenarioKind] = {
    kind.name: kind
    for kind in (
        racing.KIND,
        multi_agent.KIND,
        user_env.KIND,
    )
}


def scenario_kind(run: str | TrainConfig) -> ScenarioKind:
    """The kind of scenario ``run`` (an env's name or a run's config); an unknown env fails in one line
    (:func:`xrl_jax.config.scenario`)."""
    env = run.env if isinstance(run, TrainConfig) else run
    return KINDS[scenario(env).kind]


def make_envs(cfg: TrainConfig):
    """``(env, train_params, eval_params)`` of a run, as its kind builds them."""
    return scenario_kind(cfg).make_envs(cfg)


__all__ = ["KINDS", "ScenarioKind", "make_envs", "scenario_kind"]
