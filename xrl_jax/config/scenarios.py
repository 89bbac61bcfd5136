"""The facts of each scenario in one table: its observation layout (the set of objects whose mixture
weights are the explanation), whether it is multi-agent, what is reported over seeds, what the
report's table and comparisons show, and its yardstick. Every module asks this table rather than
testing the scenario's name."""

from __future__ import annotations

import dataclasses

from xrl_jax.config.checks import ConfigError

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


@dataclasses.dataclass(frozen=True)
class Scenario:
    """One scenario's facts (docs/carenv-single-agent.md §0, docs/carenv-intersection.md §8)."""

    name: str
    set_key: str  # the observation's set of objects: the mixture's components
    num_objects: int  # slots of that set (absent objects are all-zero rows)
    object_features: int
    state_dim: int  # the ego state vector beside the set
    multi_agent: bool
    summary_metrics: tuple[tuple[str, str], ...]  # (key, label) reported over seeds
    table_keys: tuple[str, ...]  # the report's columns; the first two are its figure's (Fig. 5/6/7)
    improvement_keys: tuple[str, ...]  # P(explainable > baseline) is taken on these
    yardstick: str  # what the report compares the agents with

    def metric_label(self, key: str) -> str:
        return dict(self.summary_metrics)[key]

    @property
    def table_metrics(self) -> tuple[tuple[str, str], ...]:
        return tuple((key, self.metric_label(key)) for key in self.table_keys)


SCENARIOS: dict[str, Scenario] = {
    "country_road": Scenario(
        "country_road", "cones_set", 100, 5, 6, False, RACING_SUMMARY,
        ("avg_return", "avg_etr"), ("avg_return",), "hand controller",
    ),
    "tracking": Scenario(
        "tracking", "trajectory_set", 25, 4, 6, False, RACING_SUMMARY,
        ("avg_return", "avg_etr"), ("avg_return",), "hand controller",
    ),
    # per agent: 8 other-vehicle slots (present, rel x/y, vel x/y, dir cos/sin) and odometry + route
    "intersection": Scenario(
        "intersection", "vehicles_set", 8, 7, 66, True, INTERSECTION_SUMMARY,
        ("avg_trips_completed", "avg_early_terminations", "avg_return"),
        ("avg_trips_completed", "avg_early_terminations"), "scripted driver",
    ),
}  # fmt: skip
MULTI_AGENT_ENVS = tuple(name for name, facts in SCENARIOS.items() if facts.multi_agent)


def scenario(name: str) -> Scenario:
    """The facts of scenario ``name`` (one of :data:`~xrl_jax.config.names.ENVS`, the table's keys)."""
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ConfigError(f"unknown scenario {name!r}; known: {', '.join(SCENARIOS)}") from None
