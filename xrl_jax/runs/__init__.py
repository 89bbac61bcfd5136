"""A run's results folder and what is read from it: the folder's layout, writes, lock and readers
(:mod:`~xrl_jax.runs.folder`, the only module that names its files), provenance
(:mod:`~xrl_jax.runs.provenance`), summaries over seeds (:mod:`~xrl_jax.runs.summary`), text tables
(:mod:`~xrl_jax.runs.tables`), figures (:mod:`~xrl_jax.runs.plots`) and the yardsticks' measured
scores they draw (:mod:`~xrl_jax.runs.references`).

The trainer writes the folder through this package, so it sits below :mod:`xrl_jax.train`; it never
imports the trainer."""

from xrl_jax.runs.folder import RunFolderError, RunLock, read_checkpoint_plan, read_rows, read_run_config
from xrl_jax.runs.plots import learning_curve_figure, plot_learning_curve, plot_sweep
from xrl_jax.runs.provenance import config_document, run_metadata
from xrl_jax.runs.references import MEASURED_YARDSTICKS, MeasuredYardstick, measured_yardstick
from xrl_jax.runs.summary import (
    aggregate_metrics,
    learning_curve,
    summarize_run,
    summary_metrics,
    training_curve,
)
from xrl_jax.runs.tables import format_curve, format_table

__all__ = [
    "MEASURED_YARDSTICKS",
    "MeasuredYardstick",
    "RunFolderError",
    "RunLock",
    "aggregate_metrics",
    "config_document",
    "format_curve",
    "format_table",
    "learning_curve",
    "learning_curve_figure",
    "measured_yardstick",
    "plot_learning_curve",
    "plot_sweep",
    "read_checkpoint_plan",
    "read_rows",
    "read_run_config",
    "run_metadata",
    "summarize_run",
    "summary_metrics",
    "training_curve",
]
