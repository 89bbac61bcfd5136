"""``experiments/explain.py`` end to end: PNG, GIF and attributions from a run folder, baselines, bad input
(racing and Intersection runs).

The default tests use smoke-preset run folders whose checkpoint holds the freshly initialised run
state (what ``run.py`` saves has the same structure), so no training has to compile; the slow test
trains a real smoke run first.
"""

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image
from train_support import load_script, one_line_error, prepare_cache

SMALL = ["--width", "320", "--height", "180", "--max-steps", "5"]
# 20 steps: the untrained cars leave the road and their slots are refilled by new cars
SMALL_INTERSECTION = ["--width", "320", "--height", "180", "--max-steps", "20"]


@pytest.fixture(scope="module")
def cli(tmp_path_factory):
    prepare_cache(tmp_path_factory.mktemp("cache"))
    return load_script("explain", "explain_cli")


def checkpoint_meta(cfg, step: int | None = None) -> dict:
    """What the trainer stores with seed 0's checkpoint (the readers check it); by default the
    final step's, so that the folder reads as a finished run."""
    from xrl_jax.train.restore import config_fingerprint

    step = cfg.total_steps if step is None else step
    return {"next_chunk": cfg.num_chunks, "seeds": [0], "step": step, "config": config_fingerprint(cfg)}


def make_run_folder(folder: Path, env: str, algo: str) -> Path:
    """A smoke-preset results folder with one seed whose checkpoint is the initial run state."""
    from xrl_jax.checkpoint import save_checkpoint
    from xrl_jax.runs import config_document
    from xrl_jax.train import get_trainer, resolve_config

    cfg = resolve_config(env, algo, "smoke")
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps(config_document(cfg, ["test"])))
    trainer = get_trainer(cfg)
    state = trainer.init(jnp.asarray(cfg.seed, jnp.int32), jnp.arange(1, dtype=jnp.int32))
    save_checkpoint(folder / "checkpoints" / "group_0", cfg.total_steps, state, checkpoint_meta(cfg))
    return folder


@pytest.fixture(scope="module")
def xdsac_run(cli, tmp_path_factory):
    return make_run_folder(tmp_path_factory.mktemp("runs") / "xdsac", "tracking", "xdsac")


def call(cli, capsys, *args):
    try:
        status = cli.main([str(a) for a in args])
    except SystemExit as exc:
        status = exc.code
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def read_lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_png_gif_and_attributions_of_a_mixture_agent(cli, xdsac_run, tmp_path, capsys):
    png = tmp_path / "frame.png"
    status, out, err = call(cli, capsys, "--run", xdsac_run, "--step", 2, "--out", png, *SMALL)
    assert status == 0, err
    assert "baseline" not in err and "attributions" in out
    assert Image.open(png).size == (320, 180)
    rows = read_lines(tmp_path / "frame.attributions.jsonl")
    assert len(rows) >= 3 and [r["step"] for r in rows] == list(range(len(rows)))
    for row in rows:
        assert row["explained"] and set(row["ego"]) == {"x", "y", "theta"} and isinstance(row["action"], int)
        np.testing.assert_allclose(sum(o["weight"] for o in row["objects"]), 1.0, rtol=1e-5)
        for item in row["objects"]:
            assert item["type"] == "trajectory_point" and np.isfinite([item["x"], item["y"]]).all()
    gif = tmp_path / "episode.gif"
    attributions = tmp_path / "episode.jsonl"
    status, _, err = call(
        cli, capsys, "--run", xdsac_run, "--out", gif, "--attributions", attributions, *SMALL
    )
    assert status == 0, err
    with Image.open(gif) as image:
        assert image.n_frames == len(read_lines(attributions))
    assert read_lines(attributions) == rows


def test_by_default_the_figures_land_in_the_run_folder(cli, xdsac_run, tmp_path, capsys, monkeypatch):
    """Without --out the figure and its attributions go to RUN/explain/, never the current folder
    (a newcomer's run from the repository's root wrote 2.3 MB there); a request that fails leaves
    no explain/ folder behind."""
    import shutil

    run = tmp_path / "results" / "tracking-xdsac-20260101-000000"
    shutil.copytree(xdsac_run, run)
    where = tmp_path / "cwd"
    where.mkdir()
    monkeypatch.chdir(where)
    one_line_error(*call(cli, capsys, "--run", run, "--seed", 1)[::2], "seed 1 out of range")
    assert not (run / "explain").exists()
    status, out, err = call(cli, capsys, "--run", run, "--step", 2, *SMALL)
    assert status == 0, err
    assert out.startswith(str(run / "explain" / "seed0_episode0_step2.png"))
    status, _, err = call(cli, capsys, "--run", run, "--format", "gif", "--episode", 1, *SMALL)
    assert status == 0, err
    assert sorted(p.name for p in (run / "explain").iterdir()) == [
        "seed0_episode0_step2.attributions.jsonl", "seed0_episode0_step2.png",
        "seed0_episode1.attributions.jsonl", "seed0_episode1.gif",
    ]  # fmt: skip
    assert Image.open(run / "explain" / "seed0_episode0_step2.png").size == (320, 180)
    assert list(where.iterdir()) == []
    one_line_error(
        *call(cli, capsys, "--run", run, "--format", "gif", "--out", "x.gif")[::2], "--out", "--format"
    )


def test_baseline_shows_only_its_distribution_and_says_so(cli, tmp_path, capsys):
    run = make_run_folder(tmp_path / "dsac", "tracking", "dsac")
    status, _, err = call(cli, capsys, "--run", run, "--out", tmp_path / "b.png", *SMALL)
    assert status == 0, err
    assert "baseline without per-object explanations" in err
    rows = read_lines(tmp_path / "b.attributions.jsonl")
    assert rows and all(not r["explained"] and r["objects"] == [] for r in rows)


def test_bad_input_fails_with_one_line(cli, xdsac_run, tmp_path, capsys):
    png = tmp_path / "x.png"
    one_line_error(*call(cli, capsys, "--run", tmp_path / "none", "--out", png)[::2], "does not exist")
    one_line_error(*call(cli, capsys, "--run", tmp_path, "--out", png)[::2], "no config.json")
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "config.json").write_text((xdsac_run / "config.json").read_text())
    one_line_error(*call(cli, capsys, "--run", empty, "--out", png)[::2], "no checkpoint")
    one_line_error(
        *call(cli, capsys, "--run", xdsac_run, "--seed", 1, "--out", png)[::2], "seed 1 out of range"
    )
    one_line_error(
        *call(cli, capsys, "--run", xdsac_run, "--episode", 3, "--out", png)[::2],
        "episode 3 out of range",
        "0..2",
    )
    one_line_error(
        *call(cli, capsys, "--run", xdsac_run, "--out", tmp_path / "x.jpg")[::2],
        "unsupported output format '.jpg'",
    )
    one_line_error(
        *call(cli, capsys, "--run", xdsac_run, "--out", tmp_path / "no" / "x.png")[::2], "does not exist"
    )
    one_line_error(
        *call(cli, capsys, "--run", xdsac_run, "--step", 9, "--out", png, *SMALL)[::2],
        "--step 9 is beyond the episode (5 steps",
    )
    one_line_error(*call(cli, capsys, "--run", xdsac_run, "--seed", -1, "--out", png)[::2], "non-negative")
    other = tmp_path / "other"
    other.mkdir()
    (other / "config.json").write_text(json.dumps({"config": {"env": "highway"}}))
    status, _, err = call(cli, capsys, "--run", other, "--out", png)
    one_line_error(status, err, "unknown scenario 'highway'", "--import")
    one_line_error(
        *call(cli, capsys, "--run", xdsac_run, "--slot", 1, "--out", png)[::2], "for intersection runs only"
    )
    assert not png.exists()


def test_an_unfinished_run_is_named_as_such(cli, xdsac_run, tmp_path, capsys):
    """A run that stopped (or diverged) early is explained from its newest good checkpoint, and the
    figure's maker is told which step that is, not silently handed an early agent."""
    import shutil

    from xrl_jax.checkpoint import save_checkpoint
    from xrl_jax.runs import read_run_config
    from xrl_jax.train.restore import shared_trainer

    cfg = read_run_config(xdsac_run)
    early = tmp_path / "early"
    early.mkdir()
    shutil.copy(xdsac_run / "config.json", early / "config.json")
    state = shared_trainer(cfg).init(jnp.asarray(cfg.seed, jnp.int32), jnp.arange(1, dtype=jnp.int32))
    save_checkpoint(early / "checkpoints" / "group_0", 64, state, checkpoint_meta(cfg, step=64))
    status, _, err = call(cli, capsys, "--run", early, "--step", 1, "--out", tmp_path / "e.png", *SMALL)
    assert status == 0 and f"using the checkpoint at step 64 of {cfg.total_steps}" in err


@pytest.mark.slow
def test_cli_on_a_trained_smoke_run(cli, tmp_path, capsys):
    run = load_script("run", "run_cli_for_explain")
    out = tmp_path / "trained"
    assert (
        run.main(
            ["--env", "country_road", "--algo", "xdsac", "--preset", "smoke", "--quiet", "--out", str(out)]
        )
        == 0
    )
    status, _, err = call(cli, capsys, "--run", out, "--out", tmp_path / "t.png", *SMALL)
    assert status == 0, err
    rows = read_lines(tmp_path / "t.attributions.jsonl")
    assert all(
        item["type"] == "cone" and item["colour"] in ("blue", "yellow") for r in rows for item in r["objects"]
    )


# ------------------------------------------------------------------------------------------------
# Intersection (multi-agent) runs
# ------------------------------------------------------------------------------------------------


def make_intersection_run_folder(folder: Path, algo: str) -> Path:
    """A smoke-preset Intersection results folder with one seed whose checkpoint holds a freshly
    initialised agent; the rest of the run state (buffer, env states, ...) is zeros, which has the
    structure run.py saves and avoids compiling the trainer's full initialisation."""
    import jax

    from xrl_jax.checkpoint import save_checkpoint
    from xrl_jax.runs import config_document
    from xrl_jax.train import resolve_config
    from xrl_jax.train.restore import shared_trainer

    # every slot computed: packing (tested in test_sets) would compile both of its branches
    cfg = resolve_config("intersection", algo, "smoke", overrides={"dense_sets": "true"})
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps(config_document(cfg, ["test"])))
    trainer = shared_trainer(cfg)  # the CLI's loads of this config then reuse it
    abstract = trainer.abstract_state(1)

    def zeros(leaf):
        if jnp.issubdtype(leaf.dtype, jax.dtypes.prng_key):
            return jax.random.split(jax.random.key(0), leaf.shape)
        return jnp.zeros(leaf.shape, leaf.dtype)

    space = trainer.env.observation_space(trainer.eval_params)
    ego_obs = {k: jnp.zeros(v.shape, v.dtype) for k, v in space.spaces.items()}
    agent_state = jax.jit(trainer.agent.init)(jax.random.PRNGKey(cfg.seed), ego_obs)
    state = jax.tree.map(zeros, abstract).replace(agent=jax.tree.map(lambda x: x[None], agent_state))
    save_checkpoint(folder / "checkpoints" / "group_0", cfg.total_steps, state, checkpoint_meta(cfg))
    return folder


@pytest.fixture(scope="module")
def intersection_run(cli, tmp_path_factory):
    return make_intersection_run_folder(tmp_path_factory.mktemp("runs") / "ix_xdsac", "xdsac")


def check_intersection_rows(rows, slot=None):
    for row in rows:
        if slot is not None:
            assert row["slot"] == slot
        if not row["alive"]:  # the slot is empty at this step: top view, nothing explained
            assert row["ego"] is None and row["objects"] == [] and row["car"] is None
            continue
        assert row["explained"] and isinstance(row["action"], int) and isinstance(row["car"], int)
        np.testing.assert_allclose(sum(o["weight"] for o in row["objects"]), 1.0, rtol=1e-5)
        neutral = [o for o in row["objects"] if o["type"] == "neutral"]
        assert len(neutral) == 1 and neutral[0]["index"] == 0
        np.testing.assert_allclose([neutral[0]["x"], neutral[0]["y"]], [row["ego"]["x"], row["ego"]["y"]])
        for item in row["objects"]:
            if item["type"] != "neutral":
                assert item["type"] == "vehicle" and item["index"] == item["row"] + 1
                assert item["slot"] != row["slot"]


def test_intersection_png_gif_and_attributions(cli, intersection_run, tmp_path, capsys):
    png = tmp_path / "ix.png"
    status, out, err = call(
        cli, capsys, "--run", intersection_run, "--step", 3, "--out", png, *SMALL_INTERSECTION
    )
    assert status == 0, err
    assert "baseline" not in err and "slot 0" in out
    assert Image.open(png).size == (320, 180)
    rows = read_lines(tmp_path / "ix.attributions.jsonl")
    assert [r["step"] for r in rows] == list(range(20))
    assert rows[0]["alive"]  # the default slot is the first one holding a car at step 0
    check_intersection_rows(rows, slot=0)
    cars = [r["car"] for r in rows if r["alive"]]
    assert cars == sorted(cars)  # a slot refilled later holds a newer car (larger spawn number)

    gif = tmp_path / "ix.gif"
    every = tmp_path / "every.jsonl"
    status, _, err = call(
        cli, capsys, "--run", intersection_run, "--slot", 2, "--all-slots", "--out", gif,
        "--attributions", every, *SMALL_INTERSECTION,
    )  # fmt: skip
    assert status == 0, err
    with Image.open(gif) as image:
        assert image.n_frames == 20
    all_rows = read_lines(every)
    check_intersection_rows(all_rows)
    assert all(r["alive"] for r in all_rows)  # one row per occupied slot and step
    assert [r for r in all_rows if r["slot"] == 0] == [r for r in rows if r["alive"]]  # same episode


def test_intersection_bad_slot_and_episode(cli, intersection_run, tmp_path, capsys):
    png = tmp_path / "x.png"
    one_line_error(
        *call(cli, capsys, "--run", intersection_run, "--slot", 8, "--out", png)[::2],
        "--slot 8 out of range",
        "0..7",
    )
    one_line_error(
        *call(cli, capsys, "--run", intersection_run, "--episode", 2, "--out", png)[::2],
        "episode 2 out of range",
    )
    assert not png.exists()


@pytest.mark.slow  # compiles a second intersection agent; the racing baseline test covers the message
def test_intersection_baseline_shows_only_its_distribution(cli, tmp_path, capsys):
    png = tmp_path / "x.png"
    run = make_intersection_run_folder(tmp_path / "ix_dsac", "dsac")
    status, _, err = call(cli, capsys, "--run", run, "--out", png, *SMALL_INTERSECTION)
    assert status == 0, err
    assert "baseline without per-object explanations" in err
    rows = read_lines(tmp_path / "x.attributions.jsonl")
    assert len(rows) == 20 and all(not r["explained"] and r["objects"] == [] for r in rows)


# ------------------------------------------------------------------------------------------------
# --stats: every seed's whole evaluation explained
# ------------------------------------------------------------------------------------------------


def test_stats_refuses_what_it_cannot_take_in_one_line(cli, xdsac_run, tmp_path, capsys):
    """Checked before anything is restored: the options of one episode's figure, a file for the
    folder, a baseline, a sweep point out of range; nothing written."""
    out = tmp_path / "stats"
    for options, fragment in (
        (["--step", 3], "--step: options of one episode's figure"),
        (["--seed", 1, "--mirrored"], "--seed, --mirrored: options"),
        (["--out", tmp_path / "stats.png"], "is a folder"),
        (["--point", 1, "--out", out], "sweep point 1 out of range"),
    ):
        one_line_error(*call(cli, capsys, "--stats", xdsac_run, *options)[::2], fragment)
    one_line_error(*call(cli, capsys, "--stats", xdsac_run, "--run", xdsac_run)[::2], "not allowed with")
    one_line_error(
        *call(cli, capsys, "--run", xdsac_run, "--deletion-episodes", 3, "--out", tmp_path / "x.png")[::2],
        "--deletion-episodes is an option of --stats",
    )
    from xrl_jax.runs import config_document
    from xrl_jax.train import resolve_config

    baseline = tmp_path / "dsac"  # refused from its config alone: no checkpoint needed
    baseline.mkdir()
    config = config_document(resolve_config("tracking", "dsac", "smoke"), ["test"])
    (baseline / "config.json").write_text(json.dumps(config))
    one_line_error(
        *call(cli, capsys, "--stats", baseline, "--deletion-episodes", 0, "--out", out)[::2],
        "dsac is a baseline",
        "--deletion-episodes 0",
    )
    one_line_error(*call(cli, capsys, "--stats", tmp_path / "none", "--out", out)[::2], "does not exist")
    assert not out.exists()


def test_stats_interrupted_says_so_in_one_line(cli, xdsac_run, tmp_path, capsys, monkeypatch):
    import xrl_jax.explain.run_statistics as run_statistics

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(run_statistics, "write_statistics", interrupted)
    status, _, err = call(cli, capsys, "--stats", xdsac_run, "--out", tmp_path / "s")
    assert status == 130 and err.strip().splitlines() == [
        "explain.py: error: interrupted; stats.json is written only once every seed is done"
    ]
    assert not (tmp_path / "s").exists()


def check_stats(folder: Path, kinds: list[str], seeds: int = 1) -> dict:
    summary = json.loads((folder / "stats.json").read_text())
    assert summary["seeds"] == seeds and summary["kinds"] == kinds
    # Every step's weight is somewhere: the kinds' shares add up to one per step (float32 weights
    # summed over a few hundred steps: 1e-5).
    np.testing.assert_allclose(sum(s["estimate"] for s in summary["kind"]["share"]), 1.0, rtol=1e-5)
    present = summary["size"]["objects_present"]["estimate"]
    assert 1 <= summary["size"]["mean"]["estimate"] <= present + 1  # + 1: the neutral component
    assert 0.0 <= summary["stability"]["mean_change"]["estimate"] <= 1.0
    situations = summary["situations"]
    steps = np.add(situations["before_early_end"]["steps"], situations["other"]["steps"])
    assert steps.tolist() == summary["steps_per_seed"]  # every step is in one situation
    assert summary["agreement"]["similarity"] == [[1.0] * seeds for _ in range(seeds)] or seeds > 1
    with Image.open(folder / "stats.png") as image:
        assert image.size[0] > 1000
    return summary


def check_deletion(deletion: dict, rankers: tuple[str, ...], metrics: list[str], seeds: int = 1) -> None:
    assert set(deletion["rankers"]) == set(rankers) and deletion["metrics"] == metrics
    assert set(deletion["against_random"]) == set(rankers) - {"random"}
    for curves in deletion["rankers"].values():
        tv = np.array(curves["tv"]["per_seed"])
        assert tv.shape == (seeds, len(deletion["ks"]))
        # Nothing deleted, nothing changed: the two passes over the same observations round alike
        # up to float32's few ulps of probabilities that sum to one.
        np.testing.assert_allclose(tv[:, 0], 0.0, atol=1e-6)
        assert np.all((tv >= -1e-6) & (tv <= 1 + 1e-6))
        # k = 0 is the agent's own evaluation for every ranker: the same actions, but each ranker's
        # program sums the float32 rewards (600 steps x 8 cars) in its own order: 1e-5 relative.
        np.testing.assert_allclose(
            np.array(curves["return"]["per_seed"])[:, 0],
            np.array(deletion["rankers"]["random"]["return"]["per_seed"])[:, 0],
            rtol=1e-5,
        )


@pytest.mark.slow  # drives every evaluation track and episode; the default tier checks the refusals
def test_stats_of_a_racing_and_an_intersection_run(cli, xdsac_run, intersection_run, tmp_path, capsys):
    status, out, err = call(cli, capsys, "--stats", xdsac_run, "--deletion-episodes", 2)
    assert status == 0, err
    assert "seed 0:" in err and "deleting by weight vs random" in out
    folder = xdsac_run / "explain" / "stats"
    summary = check_stats(folder, ["centre-line point"])
    assert len(summary["slot"]["share"]) == 25  # Tracking's 25 points ahead
    check_deletion(summary["deletion"], ("weight", "random"), ["tv", "return"])
    assert summary["deletion"]["episodes"] == 2 and (folder / "deletion.png").is_file()

    status, _, err = call(
        cli, capsys, "--stats", intersection_run, "--out", tmp_path / "ix", "--deletion-episodes", 1
    )
    assert status == 0, err
    summary = check_stats(tmp_path / "ix", ["same approach", "oncoming", "crossing", "neutral"])
    check_deletion(
        summary["deletion"], ("weight", "random"), ["tv", "return", "trips_completed", "early_terminations"]
    )


@pytest.mark.slow  # a baseline's post-hoc rankings; the default tier checks the refusals
def test_stats_of_a_baseline_are_its_post_hoc_deletion_curves(cli, tmp_path, capsys):
    run = make_run_folder(tmp_path / "dsac", "tracking", "dsac")  # discrete: exact TV, one gradient
    status, out, err = call(cli, capsys, "--stats", run, "--deletion-episodes", 2, "--out", tmp_path / "s")
    assert status == 0, err
    summary = json.loads((tmp_path / "s" / "stats.json").read_text())
    assert "size" not in summary and not (tmp_path / "s" / "stats.png").exists()
    check_deletion(summary["deletion"], ("occlusion", "gradient_x_input", "random"), ["tv", "return"])
    assert "deleting by occlusion vs random" in out
