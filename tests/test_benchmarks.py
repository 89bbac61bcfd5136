"""The benchmark tools (xrl_jax.benchmarks, experiments/bench.py and costs.py): their command lines
refuse bad input in one line, the replay batches they time are well formed, Table I's layout.
Their timings are never asserted (a shared CI machine's timings mean nothing)."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from network_support import action_size
from train_support import call, load_script, one_line_error

from xrl_jax.agents import make_agent
from xrl_jax.benchmarks import format_table_one
from xrl_jax.benchmarks.updates import real_batch
from xrl_jax.config import preset
from xrl_jax.networks import ENV_OBSERVATIONS, dummy_observation


@pytest.fixture(scope="module")
def bench():
    return load_script("bench", "bench_cli")


@pytest.mark.parametrize(
    "args, message",
    [
        (["env", "--batches", "0"], "--batches: expected a positive integer, got 0"),
        (["update", "--widths", "x"], "--widths: expected a positive integer, got 'x'"),
        (["intersection", "--vehicles", "9"], "--vehicles must lie in 1..8"),
        (["train", "--seeds", "3", "--devices", "2"], "every --seeds value must be a multiple"),
        (["update", "--env", "moon"], "invalid choice: 'moon'"),
        (["env", "--scenarios", "nope"], "--scenarios: invalid choice: 'nope'"),  # was a traceback
        (["env", "--scenarios", "intersection"], "--scenarios: invalid choice: 'intersection'"),
        (["profile", "--seeds", "0"], "--seeds: expected a positive integer, got 0"),
        (["profile", "--algo", "ppo"], "--algo: invalid choice: 'ppo'"),
        (["profile", "--set", "foo"], "--set expects KEY=VALUE, got 'foo'"),  # were tracebacks
        (["train", "--set", "log_interval"], "--set expects KEY=VALUE, got 'log_interval'"),
        (["profile", "--set", "foo=1"], "unknown setting 'foo'"),
        (["train", "--seeds", "1", "--set", "log_interval=x"], "log_interval"),
        (["rejax", "--steps", "1000"], "--steps must be a multiple of one rollout"),
        (["rejax", "--envs", "4", "--rollout-steps", "3", "--steps", "12"], "which --minibatches must split"),
        (["rejax", "--ent-coef", "nan"], "--ent-coef: expected a number in [0, 1], got nan"),
        (["rejax", "--rejax-with", "squash,tanh"], "--rejax-with: expected distinct pieces of squash, "),
        (["rejax", "--rejax-with", "squash,squash"], "--rejax-with: expected distinct pieces of"),
        (["rejax", "--truncation", "drop"], "--truncation: invalid choice: 'drop'"),
    ],
)
def test_bench_refuses_bad_input_in_one_line(bench, capsys, args, message):
    status, _, err = call(bench, capsys, *args)
    one_line_error(status, err, message)


def test_bench_rejax_ablation_options_become_the_settings_they_change(bench):
    def changes(*args):
        return bench.rejax_changes(bench.build_parser().parse_args(["rejax", *args]))

    assert changes() == {"truncation": "bootstrap"}  # ours as it trains
    parse = bench.build_parser().parse_args
    assert parse(["rejax"]).rejax_with == ()  # rejax's own PPO
    assert parse(["rejax", "--rejax-with", "global_clip, squash"]).rejax_with == ("global_clip", "squash")
    from xrl_jax.benchmarks.third_party import comparison_config

    # rejax clips its value by the ratio's range: the comparison's own ε, whatever the preset sets.
    comparison = comparison_config(seeds=1, total_steps=4000, num_envs=2, rollout_steps=1000, epochs=1,
                                   minibatches=1, width=8, depth=1)  # fmt: skip
    clip_eps = comparison.agent.clip_eps
    assert changes("--truncation", "terminal", "--ent-coef", "0", "--value-clip") == {
        "truncation": "terminal", "ent_coef": 0.0, "value_clip_eps": clip_eps,
    }  # fmt: skip


def test_bench_env_offers_every_single_agent_scenario(bench):
    import envs

    assert set(bench.RACING_SCENARIOS) == set(envs.ENV_NAMES) - set(envs.MULTI_AGENT_ENV_NAMES)


def test_bench_prints_one_json_document(bench, capsys):
    status, out, _ = call(bench, capsys, "matmul", "--size", "64")
    report = json.loads(out)
    assert status == 0 and report["command"] == "matmul" and report["machine"]["backend"] == "cpu"
    assert report["results"]["size"] == 64 and report["results"]["gflops"] > 0


@pytest.mark.parametrize("algo", ["dsac", "xsac"])
def test_real_batches_take_their_actions_from_the_agents_space(algo):
    config = preset("smoke", "country_road", algo)
    agent = make_agent(config, dummy_observation(ENV_OBSERVATIONS["country_road"]), action_size(algo))
    rows = 50
    observations = {
        name: np.arange(rows * value.size, dtype=np.float32).reshape(rows, *value.shape)
        for name, value in dummy_observation(ENV_OBSERVATIONS["country_road"]).items()
    }
    batch = real_batch(observations, 8, agent, jax.random.PRNGKey(0))
    assert batch["obs"].keys() == observations.keys() and batch["obs"]["cones_set"].shape[0] == 8
    first_values = np.asarray(batch["obs"]["cones_set"]).reshape(8, -1)[:, 0]
    assert np.all(np.isin(first_values, observations["cones_set"].reshape(rows, -1)[:, 0]))  # real rows
    action = batch["action"]
    if config.is_discrete:
        assert action.shape == (8,) and jnp.issubdtype(action.dtype, jnp.integer)
        assert int(action.min()) >= 0 and int(action.max()) < action_size(algo)
    else:
        assert action.shape == (8, action_size(algo)) and float(jnp.abs(action).max()) <= 1.0


def test_table_one_shows_missing_numbers_as_a_dash():
    row = {
        "model": "XSAC φ_d=1",
        "params": 136_455,
        "paper_params": 136_455,
        "flops_xla": 1_000_000.4,
        "flops_analytic": None,
        "paper_flops": 988_262,
        "flops_as_run": 600_000,
        "packed_capacity": 12,
        "fallback_probability": 0.0125,
    }
    header, rule, line, note = format_table_one([row])
    assert rule == "-" * len(header) and len(line) == len(header)
    assert line.split()[-6:] == ["136,455", "136,455", "1,000,000", "–", "988,262", "600,000"]
    assert "12 rows one observation reserves" in note and "probability 0.013" in note


def test_profile_names_the_model_part_of_each_op():
    """Toy HLO and trace events whose sums are known by hand: JAX's transformations are dropped from
    the op names, the backward pass is told apart, enclosing events and unknown ops are not parts."""
    from xrl_jax.benchmarks.profile import instruction_sources, model_part, op_times, time_by_part

    actor = "jit(chunk_block)/vmap()/while/body/closed_call/cond/branch_1_fun/transpose(jvp(Actor))/"
    critic = "jit(chunk_block)/vmap()/jvp(Critic)/"
    hlo = (
        f'  %dot.36 = f32[2,64,64]{{2,1,0}} dot(%a, %b), metadata={{op_name="{actor}'
        'Actor.per_object/trunk/hidden_1/dot_general" source_file="x.py"}\n'
        f'  ROOT %fusion.2 = f32[2,128]{{1,0}} fusion(%c), metadata={{op_name="{critic}'
        'Critic.q/dense_0/dot"}\n'
        "  %copy.1 = f32[4]{0} copy(%d)\n"
    )
    sources = instruction_sources(hlo)
    assert set(sources) == {"dot.36", "fusion.2"}  # copy.1 carries no metadata
    assert model_part(sources["dot.36"]) == "backward: Actor.per_object/trunk/hidden_1"
    assert model_part(sources["fusion.2"], depth=2) == "Critic.q/dense_0"
    assert model_part("jit(chunk_block)/vmap()") == "(unnamed)"
    events = [
        {"ph": "X", "name": "dot.36", "dur": 300.0},
        {"ph": "X", "name": "dot.36", "dur": 100.0},
        {"ph": "X", "name": "fusion.2", "dur": 100.0},
        {"ph": "X", "name": "copy.1", "dur": 500.0},
        {"ph": "X", "name": "ThunkExecutor::Execute", "dur": 10_000.0},  # encloses the others
        {"ph": "i", "name": "fusion.2", "dur": 7.0},  # not a complete event
    ]
    times = op_times(events)
    assert times == {"dot.36": 400.0, "fusion.2": 100.0, "copy.1": 500.0}
    parts = {p["part"]: (p["ms"], p["share"]) for p in time_by_part(times, sources)}
    assert parts == {
        "(not in the program)": (0.5, 0.5),
        "backward: Actor.per_object/trunk/hidden_1": (0.4, 0.4),
        "Critic.q/dense_0/dot": (0.1, 0.1),
    }


@pytest.mark.slow
def test_profile_of_a_smoke_chunk_accounts_for_its_ops():
    """One traced smoke chunk: parts that the model names, shares that add up to one."""
    from xrl_jax.benchmarks import bench_profile

    out = bench_profile("tracking", "xdsac", 2, None, "smoke", ["log_interval=64"])
    shares = [p["share"] for p in out["parts"]]
    assert out["ops_ms"] > 0 and abs(sum(shares) - 1) < 1e-9
    assert any("MixtureCategoricalActor" in p["part"] for p in out["parts"])


def test_bench_rejax_without_rejax_says_what_to_install(bench, capsys, monkeypatch):
    """Checked before anything trains: our side of the comparison would run first, for up to an hour."""
    import importlib.util

    real = importlib.util.find_spec
    without_rejax = lambda name, *rest: None if name == "rejax" else real(name, *rest)
    monkeypatch.setattr(importlib.util, "find_spec", without_rejax)
    status, _, err = call(bench, capsys, "rejax", "--steps", "4096")
    one_line_error(status, err, "bench.py rejax needs rejax", "gymnax-tests")
