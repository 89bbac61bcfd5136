"""Racing on tracks (Country Road, Tracking): every training episode starts on a fresh track of the
member's own feed, or with ``train_tracks`` > 0 on one drawn from a fixed bank; the evaluation drives
a fixed bank of held-out tracks, one episode per track (docs/algorithms.md §6.1)."""

from __future__ import annotations

import jax

from envs.core import VmapWrapper, vmap_env
from envs.track_feed import FreshTrackEnvs
from xrl_jax.config import TrainConfig
from xrl_jax.evaluation import make_evaluate
from xrl_jax.runs.folder import RunFolderError
from xrl_jax.tracks import cached_track_bank, racing_env
from xrl_jax.train.kinds.base import ScenarioKind


class Racing(ScenarioKind):
    name = "racing"
    rollout_velocity = "rollout/avg_track_velocity"
    figure = "track"
    endings = (("left the track", "avg_end_left_track", 2), ("time limit", "avg_end_time_limit", 2),
               ("idled out", "avg_end_idling", 2), ("invalid action", "avg_end_invalid_action", 2),
               ("distance at the end (m)", "avg_end_progress_m", 1))  # fmt: skip

    def make_envs(self, cfg: TrainConfig):
        """The fixed evaluation tracks, and for training a fixed bank (``train_tracks`` > 0) or, with
        fresh tracks, params whose one-track bank is only a template for each seed's
        :class:`envs.track_feed.TrackFeed`."""
        eval_bank = cached_track_bank(cfg.eval_track_seed, cfg.eval_episodes)
        if cfg.fresh_tracks:  # the feed brings the tracks; the bank is a one-track template
            train_bank = jax.tree.map(lambda leaf: leaf[:1], eval_bank)
        else:
            train_bank = cached_track_bank(cfg.track_seed, cfg.train_tracks)
        return racing_env(cfg.env_name, train_bank, eval_bank)

    def vector_env(self, cfg: TrainConfig, env) -> VmapWrapper:
        """Each episode on a fresh track of the member's feed (refilled half a feed at a time), or on
        one drawn from the fixed bank (auto-reset)."""
        if cfg.fresh_tracks:
            return FreshTrackEnvs(env, cfg.num_envs, cfg.track_feed_size, cfg.track_feed_size // 2)
        return vmap_env(env, cfg.num_envs)

    def make_evaluate(self, cfg: TrainConfig, env, eval_params, agent):
        return make_evaluate(env, eval_params, agent, cfg.eval_episodes)

    def check_reevaluation(self, cfg: TrainConfig, run, tracks: str) -> None:
        if tracks == "train" and cfg.fresh_tracks:
            raise RunFolderError(
                f"{run} trained on fresh tracks (train_tracks=0): no training track was driven twice, so "
                "the held-out evaluation already measures generalisation; use --tracks eval"
            )


KIND = Racing()
