"""The evaluation protocols, below the trainer: the racing scenarios on fixed held-out tracks
(:mod:`~xrl_jax.evaluation.protocol`), the Intersection on fixed episodes
(:mod:`~xrl_jax.evaluation.multiagent`), a user's env from its own reset
(:mod:`~xrl_jax.evaluation.resets`), and the yardsticks scored the same way
(:mod:`~xrl_jax.evaluation.yardsticks`). All compile to one jittable function of (key, state)."""

from xrl_jax.evaluation.multiagent import (
    EVAL_ENV_SEED,
    evaluation_episode_keys,
    evaluation_step_key,
    make_evaluate_multiagent,
    make_evaluate_multiagent_policy,
)
from xrl_jax.evaluation.protocol import (
    EARLY_TERMINATION_REWARD,
    EPISODE_FIELDS,
    make_evaluate,
    make_evaluate_policy,
    summarize_episodes,
)
from xrl_jax.evaluation.resets import make_evaluate_resets, reset_episode_keys
from xrl_jax.evaluation.yardsticks import (
    YARDSTICKS,
    evaluate_yardstick,
    hand_controller_evaluation,
    has_yardstick,
    scripted_driver_evaluation,
    yardstick_evaluation,
)

__all__ = [
    "EARLY_TERMINATION_REWARD",
    "EPISODE_FIELDS",
    "EVAL_ENV_SEED",
    "YARDSTICKS",
    "evaluate_yardstick",
    "evaluation_episode_keys",
    "evaluation_step_key",
    "hand_controller_evaluation",
    "has_yardstick",
    "make_evaluate",
    "make_evaluate_multiagent",
    "make_evaluate_multiagent_policy",
    "make_evaluate_policy",
    "make_evaluate_resets",
    "reset_episode_keys",
    "scripted_driver_evaluation",
    "summarize_episodes",
    "yardstick_evaluation",
]
