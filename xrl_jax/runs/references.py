"""The scenarios' yardsticks as measured once on the default evaluation, the one place these numbers
live: a run's learning curve draws its scenario's as a reference line when the run evaluates on the
same tracks or episodes. A report measures the yardstick afresh on its runs' own evaluation
(:mod:`xrl_jax.evaluation.yardsticks`, ``report.py --controller``); these are that measurement's
values, kept so that a run can be compared without driving the yardstick again.

Source: ``docs/results_quick/controller.json``, written by ``report.py --controller`` over the quick
runs (docs/results_quick/report.md): the hand controller of docs/carenv-single-agent.md §8.3 at its
default 8 m/s on the 100 tracks of evaluation track seed 1, and the scripted Intersection driver
(``envs/intersection_driver.py``) at its default 10 m/s on the 10 fixed evaluation episodes. Rounded
to the two decimals the README and docs quote (tests/test_learning_curve.py checks them against that
file)."""

from __future__ import annotations

import dataclasses
from typing import Any

from xrl_jax.config import scenario


@dataclasses.dataclass(frozen=True)
class MeasuredYardstick:
    """A yardstick's averages (summary metric -> value) on one evaluation: the evaluation track seed
    (None: an evaluation of fixed episodes without tracks) and the number of episodes."""

    scenario: str
    speed: float  # m/s: the controller's target speed, the driver's cruise speed
    eval_track_seed: int | None
    episodes: int
    scores: dict[str, float]

    @property
    def name(self) -> str:
        """The yardstick's name, the scenario's fact (:attr:`xrl_jax.config.Scenario.yardstick`)."""
        return scenario(self.scenario).yardstick

    def label(self, key: str) -> str:
        """The legend of its line on metric ``key``: "hand controller 36.86"."""
        return f"{self.name} {self.scores[key]:.2f}"


MEASURED_YARDSTICKS: dict[str, MeasuredYardstick] = {
    "tracking": MeasuredYardstick(
        "tracking", 8.0, 1, 100, {"avg_return": 36.86, "avg_etr": 0.06, "avg_episode_length": 574.38}
    ),
    "country_road": MeasuredYardstick(
        "country_road", 8.0, 1, 100, {"avg_return": 36.72, "avg_etr": 0.06, "avg_episode_length": 574.38}
    ),
    "intersection": MeasuredYardstick(
        "intersection", 10.0, None, 10,
        {"avg_return": 160.98, "avg_trips_completed": 26.2, "avg_early_terminations": 3.6,
         "avg_mean_velocity": 6.08},
    ),
}  # fmt: skip


def measured_yardstick(cfg: Any) -> MeasuredYardstick | None:
    """The yardstick measured on the evaluation that the run ``cfg`` uses (its env, evaluation track
    seed on tracks, and number of episodes), or None: a user's env, or another evaluation."""
    measured = MEASURED_YARDSTICKS.get(cfg.env)
    if measured is None or cfg.eval_episodes != measured.episodes:
        return None
    if measured.eval_track_seed is not None and cfg.eval_track_seed != measured.eval_track_seed:
        return None
    return measured
