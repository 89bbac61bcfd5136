"""Explanations of mixture policies: what each observed object contributes to the action, recorded
over episodes and drawn onto the bird view.

Modules, by what they hold:

* :mod:`~xrl_jax.explain.explanations`: the per-object explanation of a policy and its pruning,
  and episodes rolled out on the device with an explanation per step (its names are re-exported
  here);
* :mod:`~xrl_jax.explain.faithfulness`: faithfulness measured: objects deleted in order of importance
  (mixture weight, random, occlusion, gradient × input) and how much the action distribution (total
  variation) and the return (:class:`~xrl_jax.explain.faithfulness.DeletingAgent` in the evaluation)
  change;
* :mod:`~xrl_jax.explain.statistics`: statistics of explanations over many steps (weight maps, object
  kinds, distance, time to contact, size, step-to-step change, agreement between seeds) on plain arrays;
* :mod:`~xrl_jax.explain.evaluation_steps`, :mod:`~xrl_jax.explain.run_statistics`,
  :mod:`~xrl_jax.explain.run_deletion`, :mod:`~xrl_jax.explain.statistics_figures`: a trained run's
  whole evaluation explained, its statistics and deletion curves over seeds and their figures
  (``experiments/explain.py --stats``);
* :mod:`~xrl_jax.explain.glyphs`: what one object's action distribution looks like in a glyph;
* :mod:`~xrl_jax.explain.scenes`: where a step's observed objects are in the world;
* :mod:`~xrl_jax.explain.drawing`: glyphs drawn onto the bird view of ``envs.render``;
* :mod:`~xrl_jax.explain.episodes`: recorded episodes as frames and per-step attributions;
* :mod:`~xrl_jax.explain.figures`: how to read a figure, and the public names of the four above;
* :mod:`~xrl_jax.explain.run_figures`: a trained run's episode drawn and its attributions written
  (``experiments/explain.py``).

The figure modules need matplotlib; importing this package alone does not load them. Trained
agents come from a results folder through :func:`xrl_jax.train.restore.load_trained_agent`.
"""

from xrl_jax.explain.explanations import (
    EpisodeRecord,
    Explanation,
    MultiAgentEpisodeRecord,
    Policy,
    explain,
    keep_components,
    make_episode_rollout,
    make_multiagent_episode_rollout,
    prune,
    single_track_params,
)

__all__ = [
    "EpisodeRecord",
    "Explanation",
    "MultiAgentEpisodeRecord",
    "Policy",
    "explain",
    "keep_components",
    "make_episode_rollout",
    "make_multiagent_episode_rollout",
    "prune",
    "single_track_params",
]
