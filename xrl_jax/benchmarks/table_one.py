"""Parameters and inference FLOPs per action on Country Road shapes, beside the paper's Table I.

FLOPs are XLA's own count (``cost_analysis`` of the compiled acting function): on every one of the 100
cone slots (the paper's count), and as it runs — the per-object layers on the present cones only
(xrl_jax.sets), packed into the rows one observation reserves, weighted with the measured chance
(:mod:`xrl_jax.benchmarks.occupancy`) that an observation holds more cones and is computed on every
slot; an analytic dense-layer count beside them. The mixture actor acts through the fast path
(docs/algorithms.md §3.7): layers up to the weight-branch depth φ_d run for every object, the rest of
the trunk and the heads for the one sampled object only — which is why φ_d = 1 costs a small fraction
of φ_d = 3.
"""

from __future__ import annotations

import math
from typing import Any

import jax

import envs
from xrl_jax import distributions, networks
from xrl_jax.benchmarks.occupancy import load_occupancy, overflow_probability
from xrl_jax.benchmarks.timing import compiled_flops
from xrl_jax.config import preset
from xrl_jax.sets import Packing

# Table I of the paper: inference FLOPs per action and parameters (Country Road).
PAPER = {
    "baseline (SAC, Deep Set)": {"flops": 7_096_281, "params": 200_710},
    "XSAC φ_d=1": {"flops": 988_262, "params": 136_455},
    "XSAC φ_d=2": {"flops": 14_015_078, "params": 136_455},
    "XSAC φ_d=3": {"flops": 27_041_896, "params": 136_455},
}


def count_params(params: Any) -> int:
    """Number of scalar parameters in a pytree (works on arrays and on ``jax.eval_shape`` results)."""
    return int(sum(math.prod(leaf.shape) for leaf in jax.tree_util.tree_leaves(params)))


def dense_flops(fan_in: int, fan_out: int) -> int:
    """FLOPs of one dense layer on one input row: a multiply and an add per weight plus the bias add."""
    return 2 * fan_in * fan_out + fan_out


def mixture_actor_sample_flops(
    num_objects: int, input_dim: int, width: int, depth: int, weight_depth: int, head_outputs: int, fast: bool
) -> int:
    """Analytic dense-layer FLOPs of drawing one action from a myopic mixture actor (ReLU etc. ignored).

    Full path: every layer and head for all O objects. Fast path (§3.7): layers 1..φ_d and φ for
    all O objects, layers φ_d+1..depth and the heads (``head_outputs`` units) for one object only.
    """
    fans = [input_dim] + [width] * depth
    layer = [dense_flops(fans[i], fans[i + 1]) for i in range(depth)]
    shared = sum(layer[:weight_depth]) + dense_flops(width, 1)
    rest = sum(layer[weight_depth:]) + dense_flops(width, head_outputs)
    return num_objects * shared + (1 if fast else num_objects) * rest


def country_road_networks(algo: str, **overrides: Any) -> networks.Networks:
    """The paper's Country Road networks of ``algo`` (its continuous actions), with config overrides."""
    config = preset("paper", "country_road", algo).replace(**overrides)
    actions = envs.action_size(envs.action_space("country_road"))
    return networks.make_networks(config, networks.ENV_OBSERVATIONS["country_road"], actions)


def sac_actor_outputs(actor, params, obs) -> tuple:
    """The SAC actor's deterministic forward pass with log σ clipped as the policy clips it."""
    out = actor.apply(params, obs)
    return out.mean, distributions.clip_log_std(out.log_std, distributions.SAC_LOG_STD_MIN)


def acting_flops(nets: networks.Networks, params, obs, key) -> float:
    """XLA's FLOPs of one action: the SAC actor's deterministic forward pass, the mixture's fast path."""
    if nets.config.algo == "sac":
        return compiled_flops(lambda p, o: sac_actor_outputs(nets.actor, p, o), params, obs)
    return compiled_flops(lambda p, o, k: nets.actor.apply(p, o, k, method="sample_fast"), params, obs, key)


def policy_costs(config) -> dict:
    """Parameters and FLOPs per action of the Country Road actor of ``config`` (an ``AgentConfig`` of
    SAC or XSAC): on every cone slot (``flops_xla``), packed as it runs (``flops_packed``), and as run
    (weighted with the measured chance that an observation holds more cones than the packed rows)."""
    shape = networks.ENV_OBSERVATIONS["country_road"]
    obs = networks.dummy_observation(shape)
    obs["cones_set"] = obs["cones_set"].at[:, 0].set(1.0)  # every cone slot present: the worst case
    key = jax.random.key(0)
    actions = envs.action_size(envs.action_space("country_road"))
    nets = networks.make_networks(config.replace(dense_sets=True), shape, actions)
    params = jax.jit(nets.init_actor)(key)
    packed_only = networks.packed_only(networks.make_networks(config, shape, actions))
    dense, packed = (acting_flops(n, params, obs, key) for n in (nets, packed_only))
    capacity = Packing(nets.config.packed_rows).capacity(1, shape.num_objects)
    fallback = overflow_probability(load_occupancy()["country_road"]["histogram"], 1, capacity)
    return {
        "params": count_params(params),
        "flops_xla": dense,
        "flops_packed": packed,
        "packed_capacity": capacity,
        "fallback_probability": fallback,
        "flops_as_run": (1 - fallback) * packed + fallback * dense,
    }


def measure_table_one() -> list[dict]:
    """One row per model of Table I: parameters, FLOPs per action (every slot, packed, as run,
    analytic) and the paper's numbers."""
    shape = networks.ENV_OBSERVATIONS["country_road"]
    rows = []
    for name, algo, depth in [
        ("baseline (SAC, Deep Set)", "sac", None),
        *[(f"XSAC φ_d={d}", "xsac", d) for d in (1, 2, 3)],
    ]:
        config = preset("paper", "country_road", algo)
        config = config if depth is None else config.replace(weight_depth=depth)
        row = {"model": name, **policy_costs(config), "flops_analytic": None}
        if depth is not None:
            row["flops_analytic"] = mixture_actor_sample_flops(
                shape.num_objects,
                shape.object_features + shape.state_dim,
                config.actor_width,
                config.actor_depth,
                depth,
                6,
                fast=True,
            )
        row["paper_flops"] = PAPER[name]["flops"]
        row["paper_params"] = PAPER[name]["params"]
        rows.append(row)
    return rows


def format_table_one(rows: list[dict]) -> list[str]:
    """The rows of :func:`measure_table_one` as a table beside the paper's numbers, and what its
    columns count."""

    def number(value) -> str:
        return "–" if value is None else f"{value:,.0f}"

    header = (
        f"{'model':<26}{'params':>10}{'paper':>10}{'FLOPs (XLA)':>14}{'analytic':>14}{'paper':>14}"
        f"{'as run':>14}"
    )
    lines = [header, "-" * len(header)]
    for r in rows:
        lines.append(
            f"{r['model']:<26}{number(r['params']):>10}{number(r['paper_params']):>10}"
            f"{number(r['flops_xla']):>14}{number(r['flops_analytic']):>14}{number(r['paper_flops']):>14}"
            f"{number(r['flops_as_run']):>14}"
        )
    lines.append(
        "\nFLOPs (XLA): every one of the 100 cone slots; it includes activations and the sampling ops "
        "(+2.6 kFLOP for XSAC, -3.8 kFLOP for the baseline's deterministic forward); the analytic column "
        "counts dense layers only. As run: the present cones packed into "
        f"the {rows[0]['packed_capacity']} rows one observation reserves, or every slot with the measured "
        f"probability {rows[0]['fallback_probability']:.3f} that an observation holds more cones."
    )
    return lines
