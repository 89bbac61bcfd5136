"""A user's own env trained like a built-in scenario (``xrl_jax.register_env``): the layout is read
off the env and a bad env fails in one line; the toy env of docs/examples/nearest_goal.py trains
with XDSAC through ``run.py --import``, learns (against its own untrained agents on the same
evaluation episodes), ``report.py`` tables it, and ``explain.py`` draws its explanation figure and
attributions."""

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from train_support import call, load_script, one_line_error

import xrl_jax
from envs.core import Box, Dict, Discrete, Environment
from xrl_jax.config import ENVS, ConfigError, resolve_config
from xrl_jax.config.scenarios import BUILT_IN, scenario

EXAMPLE = Path(__file__).resolve().parents[1] / "docs" / "examples" / "nearest_goal.py"
STEPS, SEEDS, EPISODES = 4_000, 2, 32
RUN = ["--env", "nearest_goal", "--algo", "xdsac", "--preset", "quick", "--seeds", str(SEEDS),
       "--steps", str(STEPS), "--set", "eval_interval=2000", "--set", "log_interval=500",
       "--set", f"eval_episodes={EPISODES}", "--quiet"]  # fmt: skip


@pytest.fixture(scope="module")
def example():
    module = load_script_at(EXAMPLE, "nearest_goal")
    yield module
    xrl_jax.unregister_env("nearest_goal")


def load_script_at(path: Path, name: str):
    import importlib.util
    import sys

    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def test_register_env_reads_the_layout_off_the_env(example):
    facts = scenario("nearest_goal")
    assert (facts.set_key, facts.num_objects, facts.object_features, facts.state_dim) == (
        "goals_set",
        8,
        3,
        2,
    )
    assert facts.actions == "discrete" and facts.max_episode_steps == 40 and facts.kind == "user_env"
    assert BUILT_IN == ENVS and not any(scenario(name).kind == "user_env" for name in ENVS)
    cfg = resolve_config("nearest_goal", "xdsac", "smoke")
    assert cfg.env_name == "nearest_goal" and not cfg.scenario.on_tracks and not cfg.fresh_tracks
    with pytest.raises(ConfigError, match="train it with dsac, xdsac, dppo or xdppo, not xsac"):
        resolve_config("nearest_goal", "xsac", "smoke")


@pytest.mark.parametrize(
    "change, fragment",
    [
        ({"observation_space": Dict({"goals_set": Box(-1, 1, (8, 3))})}, "must be Dict"),
        ({"observation_space": Dict({"state": Box(-1, 1, (2,)), "goals_set": Box(-1, 1, (8,))})}, "(O, F)"),
        ({"action_space": Box(0, 1, (2,))}, "Box(-1, 1, (A,))"),
        ({"action_space": Discrete(5), "max_episode_steps": 0}, "max_episode_steps"),
        ({"object_xy": (0, 1)}, "object_xy"),
        ({"name": "tracking"}, "built-in"),
    ],
)
def test_an_env_the_agents_cannot_train_on_fails_in_one_line(example, change, fragment):
    change = dict(change)
    name = change.pop("name", "bad_env")
    steps = change.pop("max_episode_steps", 40)
    object_xy = change.pop("object_xy", None)

    class Changed(example.NearestGoal):
        pass

    for method, space in change.items():
        setattr(Changed, method, lambda self, params=None, space=space: space)
    env = Changed()
    with pytest.raises(ConfigError, match=fragment.replace("(", r"\(").replace(")", r"\)")) as error:
        xrl_jax.register_env(name, lambda: (env, env.default_params), steps, object_xy)
    assert "\n" not in str(error.value)
    with pytest.raises(ConfigError, match="register_env"):
        resolve_config(name if name != "tracking" else "bad_env", "xdsac", "smoke")


def untrained_returns(out: Path) -> np.ndarray:
    """(seeds, episodes) returns of the run's agents as initialised, on its evaluation episodes."""
    from xrl_jax.runs.folder import read_run_config
    from xrl_jax.train import get_trainer
    from xrl_jax.train.chunk import member_hparams

    cfg = read_run_config(out)
    trainer = get_trainer(cfg)
    members = np.arange(cfg.num_members)
    state = trainer.init(cfg.seed, members, member_hparams(cfg, trainer.agent, members))
    return np.asarray(jax.device_get(trainer.evaluate(state)[1]["return"]))


@pytest.mark.slow  # learns: 4,000 steps of 2 seeds
@pytest.mark.optimised
def test_xdsac_learns_the_toy_env_and_explains_it(example, capsys, tmp_path):
    run, explain = load_script("run", "run_custom_env"), load_script("explain", "explain_custom_env")
    out = tmp_path / "run"
    status, _, err = call(run, capsys, "--import", str(EXAMPLE), *RUN, "--out", str(out))
    assert status == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"] and set(summary["aggregate"]) >= {
        "avg_return",
        "avg_episode_length",
        "avg_terminated",
    }
    assert list((out / "checkpoints").iterdir())
    final = np.array([json.loads(path.read_text().splitlines()[-1])["episode_returns"]
                      for path in sorted((out / "eval").glob("seed_*.jsonl"))])  # fmt: skip
    assert final.shape == (SEEDS, EPISODES)
    # XDSAC evaluates greedily, so both evaluations are deterministic given the weights; the paired
    # per-episode gain must clear 3 standard errors of its mean over the 32 episodes, for every seed.
    gain = final - untrained_returns(out)
    standard_error = gain.std(axis=1, ddof=1) / np.sqrt(EPISODES)
    assert np.all(gain.mean(axis=1) > 3 * standard_error), (gain.mean(axis=1), standard_error)

    report = load_script("report", "report_custom_env")
    status, _, err = call(report, capsys, "--import", str(EXAMPLE), str(out), "--out", str(tmp_path / "rep"))
    assert status == 0, err
    table = (tmp_path / "rep" / "results_nearest_goal.md").read_text()
    assert "| final return | terminated share |" in table and "paper:" not in table

    figure, attributions = tmp_path / "explanation.png", tmp_path / "explanation.jsonl"
    args = [
        "--import",
        str(EXAMPLE),
        "--run",
        str(out),
        "--out",
        str(figure),
        "--attributions",
        str(attributions),
    ]
    status, printed, err = call(explain, capsys, *args, "--step", "1", "--threshold", "0")
    assert status == 0, err
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and "return" in printed
    rows = [json.loads(line) for line in attributions.read_text().splitlines()]
    assert rows and rows[0]["step"] == 0
    for row in rows:  # the weights of the present goals are a distribution over them
        weights = [item["weight"] for item in row["objects"]]
        assert all(item["features"][0] == 1.0 for item in row["objects"])
        # 8 float32 softmax weights, each off by a few ulps (6e-8): 1e-5 is far above their sum's error
        assert sum(weights) == pytest.approx(1.0, abs=1e-5)


@pytest.fixture
def fast_env_module():
    """tests/fast_env.py, the trivial env of the host-side tests; unregistered afterwards."""
    yield Path(__file__).with_name("fast_env.py")
    xrl_jax.unregister_env("fast")


def test_a_smoke_run_of_a_registered_env_is_reported_and_explained(fast_env_module, capsys, tmp_path):
    """The default tier's run of a user's env (the learning test above is marked slow): run.py --import
    trains tests/fast_env.py's env at the smoke preset, report.py tables it, explain.py draws it."""
    imported = ["--import", str(fast_env_module)]
    run, report, explain = (load_script(name, f"{name}_fast_env") for name in ("run", "report", "explain"))
    out = tmp_path / "run"
    status, _, err = call(run, capsys, *imported, "--env", "fast", "--algo", "xdsac", "--preset", "smoke",
                          "--seeds", "2", "--quiet", "--out", str(out))  # fmt: skip
    assert status == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["complete"]
    assert {"avg_return", "avg_episode_length", "avg_terminated"} <= set(summary["aggregate"])
    status, _, err = call(report, capsys, *imported, str(out), "--out", str(tmp_path / "rep"))
    assert status == 0, err
    table = (tmp_path / "rep" / "results_fast.md").read_text()
    assert "| final return | terminated share |" in table and "paper:" not in table
    figure, attributions = tmp_path / "explanation.png", tmp_path / "explanation.jsonl"
    drawing = ["--run", str(out), "--out", str(figure), "--attributions", str(attributions), "--step", "1"]
    status, printed, err = call(explain, capsys, *imported, *drawing, "--threshold", "0")
    assert status == 0, err
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and "return" in printed
    rows = [json.loads(line) for line in attributions.read_text().splitlines()]
    assert rows and rows[0]["step"] == 0
    for row in rows:  # 4 float32 softmax weights, each off by a few ulps: 1e-5 is far above their sum's error
        assert all(item["features"][0] == 1.0 for item in row["objects"])
        assert sum(item["weight"] for item in row["objects"]) == pytest.approx(1.0, abs=1e-5)


def test_a_run_on_an_env_nobody_registered_says_how_to_register_it(capsys, tmp_path):
    run = load_script("run", "run_custom_env_missing")
    status, _, err = call(run, capsys, "--import", str(tmp_path / "missing.py"), "--env", "nearest_goal")
    one_line_error(status, err, "--import", "no such file")
    with pytest.raises(ConfigError, match=r"xrl_jax\.register_env"):
        resolve_config("not_registered_anywhere", "xdsac", "smoke")


def test_the_evaluation_replays_fixed_episodes(example):
    """Episode i starts from the same state in every evaluation, whatever the evaluation key."""
    from xrl_jax.evaluation import reset_episode_keys

    env, params = example.make_nearest_goal()
    first, _ = reset_episode_keys(1, 4)
    again, _ = reset_episode_keys(1, 6)
    assert jnp.array_equal(first, again[:4])
    starts = jax.vmap(env.reset_env, in_axes=(0, None))(first, params)[0]["goals_set"]
    assert len({np.asarray(s).tobytes() for s in starts}) == 4


def test_a_registered_env_is_served_by_envs_make_and_envs_gymnax(example):
    import envs

    env, params = envs.make("nearest_goal")
    # (run.py --import in another test may have loaded the module again: compare by name)
    assert type(env).__name__ == "NearestGoal" and envs.action_space("nearest_goal").n == 5
    pytest.importorskip("gymnax", reason="the gymnax extra is not installed (pip install -e '.[gymnax]')")
    from envs import gymnax as carenv_gymnax

    env, params = carenv_gymnax.make("nearest_goal", flat_obs=True)
    obs, _ = env.reset(jax.random.PRNGKey(0), params)
    assert obs.shape == (2 + 8 * 3,) and params.max_steps_in_episode == 40


class Points(Environment):
    """A tiny set env for the registration checks: 2 present points in ``slots`` rows of 3 features,
    the present flag in column ``flag_column`` (0 is right)."""

    def __init__(self, slots: int = 4, flag_column: int = 0):
        self.slots, self.flag_column = slots, flag_column

    @property
    def default_params(self):
        return None

    def reset_env(self, key, params):
        flags = (jnp.arange(self.slots) < 2).astype(jnp.float32)[:, None]
        xy = jax.random.uniform(key, (self.slots, 2), minval=-1.0, maxval=1.0) * flags
        rows = jnp.concatenate([flags, xy] if self.flag_column == 0 else [xy, flags], axis=-1)
        return {"state": jnp.zeros(2), "points_set": rows}, jnp.zeros(())

    def step_env(self, key, state, action, params):
        obs, _ = self.reset_env(key, params)
        return obs, state, jnp.zeros(()), jnp.zeros((), bool), jnp.zeros((), bool), {}

    def observation_space(self, params=None):
        return Dict({"state": Box(-1, 1, (2,)), "points_set": Box(-1, 1, (self.slots, 3))})

    def action_space(self, params=None):
        return Discrete(3)


@pytest.fixture
def points():
    yield "points"
    xrl_jax.unregister_env("points")


def test_register_env_checks_the_present_flag_on_real_resets(points):
    """Rows ``[x, y, present]``: column 0 holds coordinates, which the agents would read as flags."""
    with pytest.raises(ConfigError, match=r"column 0 of 'points_set' must be the present flag") as error:
        xrl_jax.register_env(points, lambda: (Points(flag_column=2), None), 20)
    assert "\n" not in str(error.value)
    assert xrl_jax.register_env(points, lambda: (Points(), None), 20).num_objects == 4


def test_a_factory_that_returns_the_env_alone_is_told_to_return_a_pair(points):
    with pytest.raises(ConfigError, match=r"must return a pair \(env, params\), got Points \(the env alone"):
        xrl_jax.register_env(points, lambda: Points(), 20)


def test_the_time_limit_defaults_to_the_env_s_own(example):
    """One name for an env's time limit: register_env asks the env when not told."""
    env, params = example.make_nearest_goal()
    assert env.max_episode_steps(params) == 40
    facts = xrl_jax.register_env("goal_default_limit", example.make_nearest_goal)
    try:
        assert facts.max_episode_steps == 40
    finally:
        xrl_jax.unregister_env("goal_default_limit")


def register_points_from(module: str, slots: int = 4, steps: int = 20) -> None:
    """``register_env`` called from a module named ``module`` (what a run records as the registrar)."""
    namespace = {"__name__": module, "register_env": xrl_jax.register_env, "Points": Points}
    exec(f"register_env('points', lambda: (Points({slots}), None), {steps})", namespace)


@pytest.mark.parametrize(
    "change, fragment",
    [
        (dict(slots=6), "observation layout points_set (4, 3), state (2,) in the run, points_set (6, 3)"),
        (dict(steps=30), "max_episode_steps 20 in the run, 30 registered now"),
        (dict(module="another_module"), "registering module 'points_module' in the run, 'another_module'"),
    ],
)
def test_a_resume_with_another_env_than_the_run_s_is_refused_and_moves_nothing(
    points, capsys, tmp_path, change, fragment
):
    """A changed observation layout made the checkpoints unreadable: both were reported damaged and set
    aside. A changed time limit or module mixed two evaluation protocols in one run. Now the run's
    record of its env is compared first: one line, exit 2, nothing moved."""
    from xrl_jax.runs.folder import RunFolderError, read_run_config
    from xrl_jax.runs.provenance import config_document
    from xrl_jax.train.restore import config_fingerprint

    register_points_from("points_module")
    cfg = resolve_config(points, "xdsac", "smoke")
    fingerprint = config_fingerprint(cfg)
    out = tmp_path / "run"
    checkpoint = out / "checkpoints" / "group_0" / "64"
    checkpoint.mkdir(parents=True)
    (checkpoint / "state").write_text("the run's state")
    document = config_document(cfg, ["run.py"])
    (out / "config.json").write_text(json.dumps(document, indent=2, sort_keys=True))
    assert read_run_config(out).env == points  # the same env: the run reads

    register_points_from(change.pop("module", "points_module"), **change)
    assert config_fingerprint(cfg) != fingerprint  # nor would the checkpoints' fingerprint match
    run = load_script("run", "run_changed_custom_env")
    status, _, err = call(run, capsys, "--resume", str(out), "--quiet")
    one_line_error(status, err, fragment, "--import the module the run was trained with")
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == ["group_0"]
    assert (checkpoint / "state").read_text() == "the run's state"
    with pytest.raises(RunFolderError, match="registered now"):  # the folder's readers: explain, evaluate
        read_run_config(out)


def test_evaluate_py_imports_the_module_it_tells_the_user_to_import(example, capsys, tmp_path):
    """evaluate.py said "--import the module that registers it" and had no --import; now it has one,
    and a user's env run gets evaluate.py's own answer (its episodes are in eval/)."""
    from xrl_jax.runs.provenance import config_document

    out = tmp_path / "run"
    out.mkdir()
    document = config_document(resolve_config("nearest_goal", "xdsac", "smoke"), ["run.py"])
    (out / "config.json").write_text(json.dumps(document, sort_keys=True))
    evaluate = load_script("evaluate", "evaluate_custom_env")
    status, _, err = call(evaluate, capsys, "--import", str(EXAMPLE), str(out))
    one_line_error(status, err, "nearest_goal runs have no tracks")


def test_a_script_run_as_main_records_the_name_its_import_gives_it(points):
    """``python docs/examples/nearest_goal.py`` registers from ``__main__``; resuming or explaining the
    run with ``--import docs/examples/nearest_goal.py`` registers from ``nearest_goal``: one module."""
    from xrl_jax.config.user_envs import user_env_record

    namespace = {"__name__": "__main__", "__file__": "/somewhere/points_module.py", "__spec__": None,
                 "register_env": xrl_jax.register_env, "Points": Points}  # fmt: skip
    exec("register_env('points', lambda: (Points(), None), 20)", namespace)
    as_script = user_env_record(points)
    register_points_from("points_module")
    assert as_script == user_env_record(points) and as_script["module"] == "points_module"
