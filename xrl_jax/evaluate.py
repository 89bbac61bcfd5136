"""Evaluation on fixed tracks (docs/algorithms.md §6.1) and the run's results: summary, table, config.

Protocol: ``n`` episodes, episode ``i`` always on track ``i`` of a fixed evaluation bank, so every
evaluation of every seed sees the same tracks. Each agent acts in its evaluation mode (§3.8: SAC,
DSAC, XDSAC greedy; XSAC stochastic, from a separate key stream). All episodes run in parallel
(a batch of envs without auto-reset) until each has terminated or been truncated; finished
episodes are frozen by masks. Per episode: return, length, how it ended; early termination (ETR)
= terminated with a last reward below −0.5, success (SR) = terminated otherwise.

Over seeds the final score is reported as the IQM with a 95 % stratified bootstrap confidence
interval (:mod:`xrl_jax.stats`), the paper's protocol. A hyper-parameter sweep (``--sweep``) is
reported per sweep point, over that point's seeds (:func:`summarize_run`, :func:`plot_sweep`).
"""

from __future__ import annotations

import datetime
import json
import math
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from xrl_jax import stats

EARLY_TERMINATION_REWARD = -0.5
EPISODE_FIELDS = ("return", "length", "terminated", "truncated", "last_reward", "track_velocity", "cones_hit")


def make_evaluate(env, eval_params, agent, num_episodes: int, mode: str = "eval"):
    """``evaluate(key, agent_state) -> per-episode arrays`` (each ``(num_episodes,)``), jittable.

    ``eval_params`` holds a bank of at least ``num_episodes`` tracks; episode ``i`` uses track ``i``.
    ``mode`` is the agent's acting mode: "eval" (the reference's, §3.8) or "deterministic" (greedy
    for every agent, XSAC included: a diagnostic, not the paper's protocol).
    """
    if mode not in ("eval", "deterministic"):
        raise ValueError(f"an evaluation acts in mode 'eval' or 'deterministic', not {mode!r}")

    def policy(key, agent_state, obs, env_states, per_episode):
        del env_states, per_episode  # an agent sees only its observation
        return agent.act(key, agent_state, obs, mode)

    return make_evaluate_policy(env, eval_params, policy, num_episodes)


def make_evaluate_policy(env, eval_params, policy, num_episodes: int):
    """:func:`make_evaluate` for any ``policy(key, policy_state, obs, env_states, per_episode)``
    returning the batch of actions; ``evaluate(key, policy_state)``.

    A policy that reads the env state (the hand controller reads the centre line) gets it batched
    over episodes, with ``per_episode(fn)``: ``fn(env_state, params)`` vmapped over the episodes,
    each with its own track's params.
    """
    bank_size = int(eval_params.tracks.num_points.shape[0])
    if bank_size < num_episodes:
        raise ValueError(f"the evaluation bank has {bank_size} tracks, fewer than {num_episodes} episodes")
    tracks = jax.tree.map(lambda leaf: leaf[:num_episodes, None], eval_params.tracks)
    tables = getattr(eval_params, "tables", None)
    tables = None if tables is None else jax.tree.map(lambda leaf: leaf[:num_episodes, None], tables)
    max_steps = int(eval_params.max_steps)

    def own_params(track, table):
        changes = {"tracks": track} if table is None else {"tracks": track, "tables": table}
        return eval_params.replace(**changes)

    def reset_one(key, track, table):
        return env.reset_env(key, own_params(track, table))

    def step_one(key, state, action, track, table):
        return env.step_env(key, state, action, own_params(track, table))

    table_axis = 0 if tables is not None else None
    reset_all = jax.vmap(reset_one, in_axes=(0, 0, table_axis))
    step_all = jax.vmap(step_one, in_axes=(0, 0, 0, 0, table_axis))

    def per_episode(fn):
        def on_all(env_states):
            one = lambda state, track, table: fn(state, own_params(track, table))
            return jax.vmap(one, in_axes=(0, 0, table_axis))(env_states, tracks, tables)

        return on_all

    def evaluate(key, policy_state):
        reset_key, key = jax.random.split(key)
        obs, env_state = reset_all(jax.random.split(reset_key, num_episodes), tracks, tables)
        float_dtype = jnp.result_type(float)
        zeros = jnp.zeros((num_episodes,), float_dtype)
        false = jnp.zeros((num_episodes,), bool)
        record = {
            "return": zeros,
            "length": jnp.zeros((num_episodes,), jnp.int32),
            "terminated": false,
            "truncated": false,
            "last_reward": zeros,
            "track_velocity": zeros,
            "cones_hit": jnp.zeros((num_episodes,), jnp.int32),
        }

        def running(carry):
            # At most max_steps + 1 rounds, whatever the policy outputs. The env truncates every episode
            # at max_steps (and terminates it at once on a NaN action), so the count never cuts one short.
            _, _, done, _, _, t = carry
            return ~jnp.all(done) & (t < max_steps + 1)

        def body(carry):
            obs, env_state, done, record, key, t = carry
            key, act_key, step_key = jax.random.split(key, 3)
            action = policy(act_key, policy_state, obs, env_state, per_episode)
            obs, env_state, reward, terminated, truncated, info = step_all(
                jax.random.split(step_key, num_episodes), env_state, action, tracks, tables
            )
            live = ~done

            def keep(new, old):
                return jnp.where(live, new, old).astype(old.dtype)

            record = {
                "return": keep(record["return"] + reward, record["return"]),
                "length": keep(record["length"] + 1, record["length"]),
                "terminated": keep(terminated, record["terminated"]),
                "truncated": keep(truncated, record["truncated"]),
                "last_reward": keep(reward, record["last_reward"]),
                "track_velocity": keep(info["avg_track_velocity"], record["track_velocity"]),
                "cones_hit": keep(info["cones_hit"], record["cones_hit"]),
            }
            return obs, env_state, done | terminated | truncated, record, key, t + 1

        carry = (obs, env_state, false, record, key, jnp.zeros((), jnp.int32))
        return jax.lax.while_loop(running, body, carry)[3]

    return evaluate


EVAL_ENV_SEED = 0  # multi-agent evaluation: episode i always replays the env randomness of key (0, i)


def evaluation_episode_keys(episodes) -> tuple[jax.Array, jax.Array]:
    """``(reset_keys, stream_keys)`` of multi-agent evaluation episodes ``episodes`` (int array (E,)).

    Episode i's env randomness is ``fold_in(PRNGKey(EVAL_ENV_SEED), i)`` split into the reset key
    and a stream whose step-t key is ``fold_in(stream_key, t)`` (see :func:`evaluation_step_key`);
    the protocol of :func:`make_evaluate_multiagent`, so a replay of episode i (e.g. the
    explanation figures) sees exactly the evaluation's traffic.
    """
    episodes = jnp.asarray(episodes, jnp.int32)
    base = jax.random.PRNGKey(EVAL_ENV_SEED)
    episode_keys = jax.vmap(lambda i: jax.random.fold_in(base, i))(episodes.reshape(-1))
    reset_keys, stream_keys = jnp.unstack(jax.vmap(jax.random.split)(episode_keys), axis=1)
    return reset_keys.reshape(*episodes.shape, -1), stream_keys.reshape(*episodes.shape, -1)


def evaluation_step_key(stream_key: jax.Array, t) -> jax.Array:
    """The env key of step ``t`` of an evaluation episode from its stream key."""
    return jax.random.fold_in(stream_key, t)


def make_evaluate_multiagent(env, eval_params, agent, num_episodes: int):
    """``evaluate(key, agent_state) -> per-episode arrays`` for the multi-agent Intersection
    (docs/carenv-intersection.md §8.8): ``num_episodes`` episodes of ``eval_params.episode_steps`` steps with
    the evaluation cap of vehicles, every episode's env randomness fixed (episode ``i`` uses the key
    ``fold_in(PRNGKey(0), i)``, the analogue of the reference's ``reset(seed=i)``), the policy's own
    randomness (XSAC samples) from ``key``. Per episode: the return summed over all agents, and the
    env's metrics at the last step (trips completed, vehicles off the road, collided vehicles, mean
    velocity); early terminations = off-road + collided vehicles.
    """
    return make_evaluate_multiagent_policy(
        env, eval_params, lambda key, agent_state, obs: agent.act(key, agent_state, obs, "eval"), num_episodes
    )


def make_evaluate_multiagent_policy(env, eval_params, policy, num_episodes: int):
    """:func:`make_evaluate_multiagent` for any ``policy(key, policy_state, obs) -> actions`` that
    acts for every slot of a batch of episodes (obs leaves ``(episodes, 8, ...)``), e.g. the
    scripted driver; ``evaluate(key, policy_state)``."""
    steps = int(eval_params.episode_steps)
    reset_keys, stream_keys = evaluation_episode_keys(jnp.arange(num_episodes))
    reset_all = jax.vmap(env.reset, in_axes=(0, None))
    step_all = jax.vmap(env.step, in_axes=(0, 0, 0, None))
    metric_keys = ("trips_completed", "come_off_vehicles", "collided_vehicles", "mean_velocity")

    def evaluate(key, policy_state):
        obs, env_state = reset_all(reset_keys, eval_params)
        returns = jnp.zeros((num_episodes,), jnp.result_type(float))

        def body(carry, t):
            obs, env_state, returns, key = carry
            key, act_key = jax.random.split(key)
            action = policy(act_key, policy_state, obs)
            step_keys = jax.vmap(evaluation_step_key, in_axes=(0, None))(stream_keys, t)
            obs, env_state, reward, _, _, info = step_all(step_keys, env_state, action, eval_params)
            returns = returns + jnp.sum(jnp.where(info["acted"], reward, 0.0), axis=-1)
            return (obs, env_state, returns, key), {k: info[k] for k in metric_keys}

        (_, _, returns, _), metrics = jax.lax.scan(
            body, (obs, env_state, returns, key), jnp.arange(steps, dtype=jnp.int32)
        )
        last = {k: v[-1] for k, v in metrics.items()}  # the env's episode metrics after its last step
        return {
            "return": returns,
            **last,
            "early_terminations": last["come_off_vehicles"] + last["collided_vehicles"],
        }

    return evaluate


def summarize_episodes(episodes: dict[str, Any]) -> dict[str, Any]:
    """The §6.1 averages of one seed's evaluation, plus the per-episode returns (host side)."""
    if "trips_completed" in episodes:  # multi-agent: the env's metrics (docs/carenv-intersection.md §8.8)
        out = {f"avg_{k}": float(np.mean(v)) for k, v in episodes.items() if k != "return"}
        returns = np.asarray(episodes["return"], np.float64)
        return {
            "avg_return": float(returns.mean()),
            **out,
            "episode_returns": [round(float(r), 6) for r in returns],
        }
    returns = np.asarray(episodes["return"], np.float64)
    terminated = np.asarray(episodes["terminated"], bool)
    early = terminated & (np.asarray(episodes["last_reward"]) < EARLY_TERMINATION_REWARD)
    return {
        "avg_return": float(returns.mean()),
        "avg_episode_length": float(np.mean(episodes["length"])),
        "avg_etr": float(early.mean()),
        "avg_sr": float((terminated & ~early).mean()),
        "avg_track_velocity": float(np.mean(episodes["track_velocity"])),
        "avg_cones_hit": float(np.mean(episodes["cones_hit"])),
        "episode_returns": [round(float(r), 6) for r in returns],
    }


def hand_controller_evaluation(scenario: str, eval_track_seed: int, episodes: int):
    """``score(target_speed=None) -> averages``: the hand controller (:mod:`envs.hand_controller`) on a
    run's held-out tracks, ``episodes`` episodes, episode ``i`` on track ``i`` of the bank of
    ``eval_track_seed`` (the protocol of :func:`make_evaluate`), as :func:`summarize_episodes`'s
    averages. The tracks are prepared and the evaluation compiled once; the target speed is an input
    of it, so scoring several speeds costs one compilation. ``scenario`` is ``"tracking"`` or
    ``"country_road"``; the controller drives with continuous actions whichever action space the
    agents had (the tracks and rewards are the same)."""
    from envs import hand_controller
    from xrl_jax.train.tracks import cached_track_bank, racing_env

    if scenario not in ("tracking", "country_road"):
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
    import envs
    from envs.intersection_driver import DriverSettings, scripted_actions

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


def yardstick_evaluation(scenario: str, eval_track_seed: int, episodes: int):
    """The scenario's yardstick as ``score(speed=None)``: the hand controller on the racing
    scenarios' held-out tracks, the scripted driver on the Intersection (whose evaluation episodes
    are fixed, so ``eval_track_seed`` is not used there)."""
    if scenario == "intersection":
        return scripted_driver_evaluation(episodes)
    return hand_controller_evaluation(scenario, eval_track_seed, episodes)


def evaluate_yardstick(
    scenario: str, eval_track_seed: int, episodes: int, target_speed: float | None = None
) -> dict[str, Any]:
    """The scenario's yardstick at one speed (:func:`yardstick_evaluation`)."""
    return yardstick_evaluation(scenario, eval_track_seed, episodes)(target_speed)


def read_jsonl(path: Path) -> list[dict]:
    if not Path(path).exists():
        return []
    rows = []
    for line in Path(path).read_text().splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return rows


SUMMARY_METRICS = (
    ("avg_return", "final return"),
    ("avg_etr", "early-termination rate"),
    ("avg_episode_length", "episode length"),
)
MULTI_AGENT_SUMMARY_METRICS = (
    ("avg_return", "final return (all agents)"),
    ("avg_trips_completed", "completed trips"),
    ("avg_early_terminations", "early terminations"),
    ("avg_mean_velocity", "mean velocity"),
)


def summary_metrics(env: str) -> tuple[tuple[str, str], ...]:
    """The (key, label) pairs reported over seeds for ``env``."""
    return MULTI_AGENT_SUMMARY_METRICS if env == "intersection" else SUMMARY_METRICS


def _member_stems(cfg) -> list[str]:
    """The file stem of every member (point-major): ``seed_<s>``, or ``point_<p>_seed_<s>`` in a sweep."""
    from xrl_jax.train.run_folder import member_stem  # lazy: xrl_jax.train imports the trainer

    return [member_stem(cfg, member) for member in range(cfg.num_members)]


def _member_evaluations(out: Path, cfg) -> list[dict[int, dict]]:
    """Per member (point-major; in a plain run, per seed), its evaluation rows by step (the last row
    of a step wins: a resumed run rewrites)."""
    return [
        {r["step"]: r for r in read_jsonl(out / "eval" / f"{stem}.jsonl") if "step" in r}
        for stem in _member_stems(cfg)
    ]


def _aggregate(scores: np.ndarray) -> dict[str, Any]:
    """IQM with its 95 % stratified bootstrap CI over seeds, the mean and the number of seeds."""
    interval = stats.stratified_bootstrap_ci(scores, stats.iqm, confidence=0.95)
    return {**interval.as_dict(), "mean": float(scores.mean()), "n": int(scores.size)}


def aggregate_metrics(rows: list[dict], env: str) -> dict[str, Any]:
    """:func:`_aggregate` of every summary metric over ``rows`` (one per seed); non-finite ones skipped."""
    result = {}
    for key, _ in summary_metrics(env):
        scores = np.array([row.get(key, np.nan) for row in rows], np.float64)
        if np.all(np.isfinite(scores)):
            result[key] = _aggregate(scores)
    return result


def learning_curve(out: str | Path, cfg, point: int | None = None) -> list[dict[str, Any]]:
    """The evaluation curve over seeds: at every evaluation step that all seeds reached, each summary
    metric's IQM, 95 % stratified bootstrap CI, mean and per-seed values. A sweep has one curve per
    point: pass ``point`` (curves never mix points)."""
    evaluations = _member_evaluations(Path(out), cfg)
    if point is None:
        if cfg.num_points > 1:
            raise ValueError(
                f"a sweep has one learning curve per point; pass point= (0..{cfg.num_points - 1})"
            )
        point = 0
    if not 0 <= point < cfg.num_points:
        raise ValueError(f"point {point} is not in 0..{cfg.num_points - 1}")
    return _curve([evaluations[m] for m in cfg.point_members(point)], cfg.env)


def _curve(evaluations: list[dict[int, dict]], env: str) -> list[dict[str, Any]]:
    steps = sorted(set.intersection(*(set(rows) for rows in evaluations))) if evaluations else []
    curve = []
    for step in steps:
        rows = [by_step[step] for by_step in evaluations]
        point = {"step": step, **aggregate_metrics(rows, env)}
        for key in point:
            if key != "step":
                point[key]["per_seed"] = [float(row[key]) for row in rows]
        curve.append(point)
    return curve


# What every record says about its member (run_folder.member_fields): in a plain run "point" is 0
# and "sweep" is {}, which the summary leaves out so that it reads as before sweeps existed.
_SWEEP_RECORD_FIELDS = ("point", "sweep")


def summarize_run(out: str | Path, cfg) -> dict[str, Any]:
    """Final evaluation of every seed and, over seeds, the IQM with its 95 % stratified bootstrap CI;
    ``curve`` holds the same statistics at every evaluation step (:func:`learning_curve`).

    A sweep (``cfg.num_points > 1``) is summarised per point, never over points: top-level
    ``aggregate`` is ``{}`` and ``curve`` is ``[]``; ``seeds`` lists the member stems
    (``point_<p>_seed_<s>``) with a final evaluation, ``complete`` says whether every member has one,
    ``per_seed`` (and ``training_tracks``) are keyed by member stem, and ``sweep`` holds
    ``{"fields": [name, ...], "points": [{"point": p, "values": {name: value}, "seeds": [seed with a
    final evaluation], "complete": bool, "aggregate": {...}, "curve": [...]}, ...]}`` with
    ``aggregate`` and ``curve`` as in a plain run, over that point's seeds.
    """
    out = Path(out)
    evaluations = _member_evaluations(out, cfg)
    stems = _member_stems(cfg)
    final = cfg.total_steps
    summary: dict[str, Any] = {"env": cfg.env, "algo": cfg.algo, "preset": cfg.preset, "steps": final}
    if cfg.num_points == 1:
        finals = {seed: rows[final] for seed, rows in enumerate(evaluations) if final in rows}
        summary |= {
            "seeds": sorted(finals),
            "complete": len(finals) == cfg.num_seeds,
            "per_seed": {str(s): _per_seed_row(r, drop=_SWEEP_RECORD_FIELDS) for s, r in finals.items()},
            "aggregate": aggregate_metrics([finals[s] for s in sorted(finals)], cfg.env) if finals else {},
            "curve": _curve(evaluations, cfg.env),
        }
    else:
        finished = [m for m, rows in enumerate(evaluations) if final in rows]
        points = []
        for point, values in enumerate(cfg.sweep_points):
            members = cfg.point_members(point)
            finals = [evaluations[m][final] for m in members if final in evaluations[m]]
            points.append({
                "point": point,
                "values": dict(values),
                "seeds": [cfg.member_point_seed(m)[1] for m in members if final in evaluations[m]],
                "complete": len(finals) == cfg.num_seeds,
                "aggregate": aggregate_metrics(finals, cfg.env) if finals else {},
                "curve": _curve([evaluations[m] for m in members], cfg.env),
            })  # fmt: skip
        summary |= {
            "seeds": [stems[m] for m in finished],
            "complete": len(finished) == cfg.num_members,
            "per_seed": {stems[m]: _per_seed_row(evaluations[m][final]) for m in finished},
            "aggregate": {},  # over points it would mix hyper-parameters: see sweep.points[i].aggregate
            "curve": [],  # likewise: sweep.points[i].curve
            "sweep": {"fields": [name for name, _ in cfg.sweep], "points": points},
        }
    if not cfg.multi_agent:
        summary["training_tracks"] = _training_tracks(out, cfg)
    return summary


def _per_seed_row(row: dict, drop: tuple[str, ...] = ()) -> dict:
    return {k: v for k, v in row.items() if k != "episode_returns" and k not in drop}


def _training_tracks(out: Path, cfg) -> dict[str, Any]:
    """What the seeds trained on: a fixed bank, or fresh tracks with each seed's count of distinct
    tracks driven and of resets that found its feed empty (from its last metrics line), keyed by
    seed (``"0"``) in a plain run and by member stem (``"point_0_seed_0"``) in a sweep."""
    if not cfg.fresh_tracks:
        return {"fresh": False, "bank": cfg.train_tracks}
    used, reused = {}, {}
    for member, stem in enumerate(_member_stems(cfg)):
        key = str(cfg.member_point_seed(member)[1]) if cfg.num_points == 1 else stem
        rows = [r for r in read_jsonl(out / "metrics" / f"{stem}.jsonl") if "rollout/tracks_used" in r]
        if rows:
            used[key] = int(rows[-1]["rollout/tracks_used"])
            reused[key] = int(rows[-1]["rollout/tracks_reused"])
    return {"fresh": True, "distinct_per_seed": used, "reused_per_seed": reused}


def format_training_tracks(summary: dict[str, Any]) -> str | None:
    """One line on the training tracks (None for intersection runs and older summaries)."""
    tracks = summary.get("training_tracks")
    if tracks is None:
        return None
    if not tracks["fresh"]:
        return f"training tracks: a fixed bank of {tracks['bank']}"
    used = list(tracks["distinct_per_seed"].values())
    if not used:
        return "training tracks: fresh (no metrics yet)"
    reused = sum(tracks["reused_per_seed"].values())
    spread = f" (min {min(used):,}, max {max(used):,})" if len(used) > 1 else ""
    return (
        f"training tracks: fresh, {sum(used) / len(used):,.0f} distinct per {_run_unit(summary)}{spread}; "
        f"{reused:,} resets reused a track"
    )


def _run_unit(summary: dict[str, Any]) -> str:
    """What a summary's rows are: seeds, or members (a seed at a sweep point) in a sweep."""
    return "member" if summary.get("sweep") else "seed"


def _format_value(value: Any) -> str:
    return f"{value:g}" if isinstance(value, int | float) else str(value)


def _format_interval(agg: dict[str, Any] | None) -> str:
    return f"{agg['estimate']:.3f} [{agg['low']:.3f}, {agg['high']:.3f}]" if agg else "-"


def format_table(summary: dict[str, Any]) -> str:
    """A plain-text table of the aggregate scores (IQM and 95 % stratified bootstrap CI over seeds);
    for a sweep, one row per point: its values, IQM [95 % CI] of the first two summary metrics
    (final return and early-termination rate; for intersection, return and completed trips) and its
    number of seeds with a final evaluation (``*``: not all of them have one yet)."""
    title = f"{summary['env']} / {summary['algo']} ({summary['preset']}), {summary['steps']} steps per seed"
    if summary.get("sweep"):
        return _format_sweep_table(summary, title)
    lines = [title, f"{'metric':<26} {'IQM':>10} {'95% CI':>22} {'mean':>10} {'seeds':>6}"]
    for key, label in summary_metrics(summary["env"]):
        agg = summary["aggregate"].get(key)
        if agg is None:
            continue
        ci = f"[{agg['low']:.3f}, {agg['high']:.3f}]"
        lines.append(f"{label:<26} {agg['estimate']:>10.3f} {ci:>22} {agg['mean']:>10.3f} {agg['n']:>6d}")
    if not summary["aggregate"]:
        lines.append("(no final evaluation yet)")
    tracks = format_training_tracks(summary)
    if tracks:
        lines.append(tracks)
    return "\n".join(lines)


def _format_sweep_table(summary: dict[str, Any], title: str) -> str:
    sweep = summary["sweep"]
    chosen = summary_metrics(summary["env"])[:2]
    widths = [max(8, len(name)) for name in sweep["fields"]]
    header = "".join(f"{name:>{w}} " for name, w in zip(sweep["fields"], widths, strict=True))
    header += "".join(f" {label + ' IQM [95% CI]':>34}" for _, label in chosen) + f" {'seeds':>6}"
    lines = [title, header]
    for point in sweep["points"]:
        values = [_format_value(point["values"][name]) for name in sweep["fields"]]
        row = "".join(f"{value:>{w}} " for value, w in zip(values, widths, strict=True))
        row += "".join(f" {_format_interval(point['aggregate'].get(key)):>34}" for key, _ in chosen)
        seeds = f"{len(point['seeds'])}{'' if point['complete'] else '*'}"
        lines.append(row + f" {seeds:>6}")
    if not all(point["complete"] for point in sweep["points"]):
        lines.append("* not every seed of the point has a final evaluation yet")
    tracks = format_training_tracks(summary)
    if tracks:
        lines.append(tracks)
    return "\n".join(lines)


def _point_label(values: dict[str, Any]) -> str:
    """``{"kappa": 0.01, "gamma": 0.99}`` -> ``"kappa=0.01, gamma=0.99"``."""
    return ", ".join(f"{name}={_format_value(value)}" for name, value in values.items())


def _curve_label(label: str) -> str:
    """'final return' -> 'return': a curve point is not final."""
    return label.removeprefix("final ")


def format_curve(summary: dict[str, Any], metrics: int = 2) -> str:
    """The learning curve as a plain-text table: per evaluation step, IQM [95 % CI] of the first
    ``metrics`` summary metrics."""
    chosen = summary_metrics(summary["env"])[:metrics]
    header = f"{'step':>10}" + "".join(f"  {_curve_label(label):>30}" for _, label in chosen)
    if summary.get("sweep"):  # one line per point: the last step all its seeds reached
        title = "learning curves per sweep point: IQM [95% CI] at the last step all its seeds reached"
        lines = [f"{title} (every step: summary.json)", header + "  point"]
        for point in summary["sweep"]["points"]:
            last = point["curve"][-1] if point["curve"] else {"step": "-"}
            cells = "".join(f"  {_format_interval(last.get(key)):>30}" for key, _ in chosen)
            lines.append(f"{last['step']:>10}{cells}  {_point_label(point['values'])}")
        return "\n".join(lines)
    lines = ["learning curve (IQM [95% CI] over seeds)", header]
    for point in summary.get("curve", []):
        cells = []
        for key, _ in chosen:
            agg = point.get(key)
            cells.append(f"{agg['estimate']:.3f} [{agg['low']:.3f}, {agg['high']:.3f}]" if agg else "-")
        lines.append(f"{point['step']:>10}" + "".join(f"  {cell:>30}" for cell in cells))
    return "\n".join(lines)


def plot_learning_curve(summary: dict[str, Any], path: str | Path, metrics: int = 2) -> Path:
    """Save the learning curve (IQM line, 95 % CI band, thin per-seed lines) of the first ``metrics``
    summary metrics as one PNG panel each; returns ``path``. For a sweep, one IQM line (and a light
    CI band) per point, labelled by its values, without per-seed lines."""
    from matplotlib.figure import Figure  # no pyplot: no GUI backend, safe in threads and on servers

    chosen = summary_metrics(summary["env"])[:metrics]
    if summary.get("sweep"):
        return _plot_sweep_curves(summary, Path(path), chosen)
    curve = summary.get("curve", [])
    figure = Figure(figsize=(4.2 * len(chosen), 3.2), layout="constrained")
    axes = figure.subplots(1, len(chosen), squeeze=False)[0]
    for ax, (key, label) in zip(axes, chosen, strict=True):
        points = [p for p in curve if key in p]
        steps = np.array([p["step"] for p in points])
        if points:
            per_seed = np.array([p[key]["per_seed"] for p in points])
            ax.plot(steps, per_seed, color="0.75", linewidth=0.8)
            ax.fill_between(
                steps, [p[key]["low"] for p in points], [p[key]["high"] for p in points],
                color="tab:blue", alpha=0.25, linewidth=0, label="95 % CI",
            )  # fmt: skip
            ax.plot(steps, [p[key]["estimate"] for p in points], color="tab:blue", marker="o", label="IQM")
            ax.legend(loc="best", fontsize="small")
        ax.set_xlabel("environment steps per seed")
        format_step_axis(ax)
        ax.set_title(_curve_label(label))
        ax.grid(alpha=0.3)
    seeds = max((p[key]["n"] for p in curve for key, _ in chosen if key in p), default=0)
    figure.suptitle(f"{summary['env']} / {summary['algo']} ({summary['preset']}), {seeds} seeds")
    path = Path(path)
    figure.savefig(path, dpi=110)
    return path


def _plot_sweep_curves(summary: dict[str, Any], path: Path, chosen) -> Path:
    from matplotlib.figure import Figure

    points = summary["sweep"]["points"]
    figure = Figure(figsize=(4.2 * len(chosen), 3.2), layout="constrained")
    axes = figure.subplots(1, len(chosen), squeeze=False)[0]
    for ax, (key, label) in zip(axes, chosen, strict=True):
        for index, point in enumerate(points):
            rows = [p for p in point["curve"] if key in p]
            if not rows:
                continue
            color = f"C{index % 10}"
            steps = [p["step"] for p in rows]
            low, high = [p[key]["low"] for p in rows], [p[key]["high"] for p in rows]
            ax.fill_between(steps, low, high, color=color, alpha=0.12, linewidth=0)
            ax.plot(steps, [p[key]["estimate"] for p in rows], color=color, marker="o", markersize=3,
                    label=_point_label(point["values"]))  # fmt: skip
        if ax.has_data():
            ax.legend(loc="best", fontsize="x-small")
        ax.set_xlabel("environment steps per seed")
        format_step_axis(ax)
        ax.set_title(_curve_label(label) + " (IQM, 95 % CI)")
        ax.grid(alpha=0.3)
    figure.suptitle(f"{summary['env']} / {summary['algo']} ({summary['preset']}), sweep over "
                    f"{', '.join(summary['sweep']['fields'])}")  # fmt: skip
    figure.savefig(path, dpi=110)
    return path


def sweep_x_scale(values) -> tuple[str, float | None]:
    """When the swept values span at least two orders of magnitude: ``("symlog", linthresh)`` if
    they span zero (include it, or both signs; e.g. kappa = -0.01 … 0.1), with the smallest non-zero
    magnitude as the linear threshold, and ``("log", None)`` if they are all positive (e.g. learning
    rates 1e-5 … 1e-3); else ``("linear", None)``."""
    values = np.asarray(values, np.float64)
    magnitudes = np.abs(values[values != 0])
    if magnitudes.size < 2 or magnitudes.max() < 100 * magnitudes.min():
        return "linear", None
    if values.min() <= 0 <= values.max():
        return "symlog", float(magnitudes.min())
    return ("log", None) if values.min() > 0 else ("linear", None)


def plot_sweep(summary: dict[str, Any], path: str | Path, baseline: dict[str, Any] | None = None) -> Path:
    """Save the sweep figure (the paper's Fig. 8 style) as a PNG; returns ``path``.

    Two panels, the first two summary metrics (final return and early-termination rate; for
    intersection, return and completed trips): x is the swept value of the first field, y the IQM
    over the point's seeds with its 95 % CI as error bars. With more than one swept field, one line
    per combination of the other fields' values. ``baseline`` (the summary of a plain run, e.g.
    DSAC) adds a horizontal line at its final IQM with its CI shaded, labelled ``baseline: <algo>``.
    The x scale is symlog when the values span zero and several orders of magnitude, log when they
    are positive and span several, else linear (:func:`sweep_x_scale`).
    """
    from matplotlib.figure import Figure  # no pyplot: no GUI backend, safe in threads and on servers

    sweep = summary.get("sweep")
    if not sweep:
        raise ValueError("plot_sweep needs the summary of a sweep (summary['sweep'] is missing)")
    fields = sweep["fields"]
    first, others = fields[0], fields[1:]
    lines: dict[tuple, list[dict]] = {}  # the other fields' values -> the points on that line
    for point in sweep["points"]:
        lines.setdefault(tuple(point["values"][name] for name in others), []).append(point)
    xs = sorted({point["values"][first] for point in sweep["points"]})
    scale, linthresh = sweep_x_scale(xs)
    chosen = summary_metrics(summary["env"])[:2]
    figure = Figure(figsize=(4.4 * len(chosen), 3.4), layout="constrained")
    axes = figure.subplots(1, len(chosen), squeeze=False)[0]
    for ax, (key, label) in zip(axes, chosen, strict=True):
        if scale == "symlog":  # before plotting, so that the margins apply on this scale
            ax.set_xscale("symlog", linthresh=linthresh)
        elif scale == "log":
            ax.set_xscale("log")
        for index, (rest, points) in enumerate(lines.items()):
            done = sorted((p for p in points if key in p["aggregate"]), key=lambda p: p["values"][first])
            if not done:
                continue
            x = np.array([p["values"][first] for p in done], np.float64)
            est = np.array([p["aggregate"][key]["estimate"] for p in done])
            low = np.array([p["aggregate"][key]["low"] for p in done])
            high = np.array([p["aggregate"][key]["high"] for p in done])
            name = _point_label(dict(zip(others, rest, strict=True))) if others else "IQM, 95 % CI"
            ax.errorbar(x, est, yerr=[est - low, high - est], color=f"C{index % 10}", marker="o",
                        capsize=3, linewidth=1.2, label=name)  # fmt: skip
        agg = (baseline or {}).get("aggregate", {}).get(key)
        if agg is not None:
            ax.axhspan(agg["low"], agg["high"], color="0.5", alpha=0.2, linewidth=0)
            ax.axhline(agg["estimate"], color="0.3", linestyle="--", linewidth=1.2,
                       label=f"baseline: {baseline['algo']}")  # fmt: skip
        ax.set_xticks(xs, [_format_value(x) for x in xs], fontsize="small", rotation=45 if len(xs) > 5 else 0)
        ax.minorticks_off()
        ax.set_xlabel(first)
        ax.set_title(label)
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="best", fontsize="x-small")
    seeds = max((len(p["seeds"]) for p in sweep["points"]), default=0)
    title = f"{summary['env']} / {summary['algo']} ({summary['preset']})"
    figure.suptitle(f"{title}: IQM over up to {seeds} seeds per point")
    path = Path(path)
    figure.savefig(path, dpi=110)
    return path


def format_step_axis(ax: Any) -> None:
    """Step ticks as 20k, 1M: written out in full they run into each other beyond ~50k steps."""
    from matplotlib.ticker import EngFormatter, MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(nbins=5, steps=[1, 2, 2.5, 5, 10], integer=True))
    ax.xaxis.set_major_formatter(EngFormatter(sep=""))


def _git_commit(repo: Path) -> dict[str, Any]:
    def git(*args):
        result = subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, timeout=10)
        return result.stdout.strip() if result.returncode == 0 else None

    try:
        commit = git("rev-parse", "HEAD")
        status = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}
    return {"commit": commit, "dirty": None if status is None else bool(status)}


def versions() -> dict[str, str | None]:
    import importlib.metadata as md

    out: dict[str, str | None] = {"python": platform.python_version()}
    for name in ("jax", "jaxlib", "flax", "optax", "orbax-checkpoint", "distrax", "numpy", "xrl-jax"):
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            out[name] = None
    import envs

    out["envs"] = envs.__version__
    return out


def run_metadata(argv: list[str] | None = None) -> dict[str, Any]:
    """Versions, git commit, device and command line: everything needed to reproduce the run."""
    device = jax.devices()[0]
    return {
        "versions": versions(),
        "git": _git_commit(Path(__file__).resolve().parents[1]),
        "device": {"backend": jax.default_backend(), "kind": getattr(device, "device_kind", str(device))},
        "command": [sys.executable, *(sys.argv if argv is None else argv)],
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }


def config_document(cfg, argv: list[str] | None = None) -> dict[str, Any]:
    """The content of ``config.json``: the fully resolved config (incl. resolved agent defaults)."""
    from xrl_jax.agents import make_hparams

    agent = cfg.agent
    action_size = 12 if agent.is_discrete else 3
    hp = make_hparams(agent, action_size)
    resolved = {
        "alpha_lr": agent.resolved_alpha_lr(),
        "epsilon_random": agent.resolved_epsilon_random(),
        "target_entropy": float(hp.target_entropy),
        "log_std_min": agent.resolved_log_std_min(),
        "env_name": cfg.env_name,
        "buffer_layout": cfg.buffer_layout,
        "updates_per_seed": max(0, cfg.total_steps - cfg.warmup_steps),
    }
    doc = {"config": cfg.to_dict(), "resolved": resolved, **run_metadata(argv)}
    if cfg.num_points > 1:  # every member's seed, point and values, in the order of the member axis
        from xrl_jax.train.run_folder import member_fields, member_stem

        doc["members"] = [
            {"member": m, "file": member_stem(cfg, m), **member_fields(cfg, m)}
            for m in range(cfg.num_members)
        ]
    json.dumps(doc)  # fail early on anything not serialisable
    return doc


def isfinite_or_none(x: float) -> float | None:
    return x if math.isfinite(x) else None
