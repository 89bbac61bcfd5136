"""The facts of each scenario in one table: its observation layout (the set of objects whose mixture
weights are the explanation), its kind, what is reported over seeds, what the report's table and
comparisons show, and its yardstick. Every module asks this table rather than testing the scenario's
name. A user's own env joins the table through :func:`xrl_jax.custom_envs.register_env`, which reads
its facts off the env (:func:`register_scenario`).

The *kind* names the object that answers how such a scenario trains, evaluates, reports and is
explained (:mod:`xrl_jax.train.kinds`: racing on tracks, the multi-agent Intersection, a user's env).
This layer is below the trainer and cannot ask that object: what the configuration itself needs of a
kind is written here as data, the scenario's own facts (whether it drives on tracks, how many agent
slots an env has)."""

from __future__ import annotations

import dataclasses

from xrl_jax.config.checks import ConfigError
from xrl_jax.config.names import MAX_VEHICLES

RACING_SUMMARY = (
    ("avg_return", "final return"),
    ("avg_etr", "early-termination rate"),
    ("avg_episode_length", "episode length"),
)
INTERSECTION_SUMMARY = (
    ("avg_return", "final return (all agents)"),
    ("avg_trips_completed", "completed trips"),
    ("avg_early_terminations", "early terminations"),
    ("avg_mean_velocity", "mean velocity"),
)
CUSTOM_SUMMARY = (  # a user's env: what every episode has
    ("avg_return", "final return"),
    ("avg_episode_length", "episode length"),
    ("avg_terminated", "terminated share"),
)


@dataclasses.dataclass(frozen=True)
class Scenario:
    """One scenario's facts (docs/carenv-single-agent.md §0, docs/carenv-intersection.md §8)."""

    name: str
    set_key: str  # the observation's set of objects: the mixture's components
    num_objects: int  # slots of that set (absent objects are all-zero rows)
    object_features: int
    state_dim: int  # the ego state vector beside the set
    kind: str  # its kind's name in xrl_jax.train.kinds: "racing", "multi_agent" or "user_env"
    summary_metrics: tuple[tuple[str, str], ...]  # (key, label) reported over seeds
    table_keys: tuple[str, ...]  # the report's columns; the first two are its figure's (Fig. 5/6/7)
    improvement_keys: tuple[str, ...]  # P(explainable > baseline) is taken on these
    yardstick: str  # what the report compares the agents with
    on_tracks: bool = True  # racing: trains on generated tracks, evaluates on fixed ones
    # Agents per env, each an actor with its own observation: a multi-agent env's vehicle slots. Their
    # transitions are stored packed, one per row (a varying number per step), with next_obs.
    agent_slots: int = 1
    actions: str = "both"  # "both" (a *_discrete variant in envs), "continuous" or "discrete" (one env)
    max_episode_steps: int | None = None  # a user's env: where the evaluation stops an episode
    object_xy: tuple[int, int] | None = None  # a user's env: the object features that are its x, y

    def metric_label(self, key: str) -> str:
        return dict(self.summary_metrics)[key]

    @property
    def table_metrics(self) -> tuple[tuple[str, str], ...]:
        return tuple((key, self.metric_label(key)) for key in self.table_keys)


SCENARIOS: dict[str, Scenario] = {
    "country_road": Scenario(
        "country_road", "cones_set", 100, 5, 6, "racing", RACING_SUMMARY,
        ("avg_return", "avg_etr"), ("avg_return",), "hand controller",
    ),
    "tracking": Scenario(
        "tracking", "trajectory_set", 25, 4, 6, "racing", RACING_SUMMARY,
        ("avg_return", "avg_etr"), ("avg_return",), "hand controller",
    ),
    # per agent: 8 other-vehicle slots (present, rel x/y, vel x/y, dir cos/sin) and odometry + route
    "intersection": Scenario(
        "intersection", "vehicles_set", 8, 7, 66, "multi_agent", INTERSECTION_SUMMARY,
        ("avg_trips_completed", "avg_early_terminations", "avg_return"),
        ("avg_trips_completed", "avg_early_terminations"), "scripted driver", on_tracks=False,
        agent_slots=MAX_VEHICLES,
    ),
}  # fmt: skip
BUILT_IN = tuple(SCENARIOS)  # == names.ENVS (a test checks)


def scenario(name: str) -> Scenario:
    """The facts of scenario ``name``: a built-in one (:data:`~xrl_jax.config.names.ENVS`) or one
    registered in this process."""
    try:
        return SCENARIOS[name]
    except (KeyError, TypeError):
        raise ConfigError(
            f"unknown scenario {name!r}; known: {', '.join(SCENARIOS)} (a user's env is known once "
            "xrl_jax.register_env has registered it in this process; scripts: --import the module that does)"
        ) from None


def known_envs() -> tuple[str, ...]:
    """The built-in scenarios and the user's envs registered so far."""
    return tuple(SCENARIOS)


def custom_scenario(
    name: str, set_key: str, num_objects: int, object_features: int, state_dim: int, actions: str,
    max_episode_steps: int, object_xy: tuple[int, int] | None = None,
) -> Scenario:  # fmt: skip
    """The facts of a user's single-agent env, its evaluation the env's own resets."""
    return Scenario(
        name, set_key, num_objects, object_features, state_dim, "user_env", CUSTOM_SUMMARY,
        ("avg_return", "avg_terminated"), ("avg_return",), "none", on_tracks=False, actions=actions,
        max_episode_steps=max_episode_steps, object_xy=object_xy,
    )  # fmt: skip


def register_scenario(facts: Scenario) -> None:
    """Add (or replace) a user's scenario; a built-in one cannot be replaced."""
    if facts.name in BUILT_IN:
        raise ConfigError(f"{facts.name!r} is a built-in scenario; register your env under another name")
    SCENARIOS[facts.name] = facts


def unregister_scenario(name: str) -> None:
    """Forget a user's scenario (built-in ones stay)."""
    if name not in BUILT_IN:
        SCENARIOS.pop(name, None)
