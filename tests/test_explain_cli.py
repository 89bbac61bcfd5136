"""``experiments/explain.py`` end to end: PNG, GIF and attributions from a run folder, baselines, bad input.

The default tests use smoke-preset run folders whose checkpoint holds the freshly initialised run
state (what ``run.py`` saves has the same structure), so no training has to compile; the slow test
trains a real smoke run first.
"""

import importlib.util
import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image
from train_support import prepare_cache

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["--width", "320", "--height", "180", "--max-steps", "5"]


def load_script(name):
    spec = importlib.util.spec_from_file_location(f"{name}_cli", ROOT / "experiments" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def cli(tmp_path_factory):
    prepare_cache(tmp_path_factory.mktemp("cache"))
    return load_script("explain")


def make_run_folder(folder: Path, env: str, algo: str) -> Path:
    """A smoke-preset results folder with one seed whose checkpoint is the initial run state."""
    from xrl_jax.checkpoint import save_checkpoint
    from xrl_jax.evaluate import config_document
    from xrl_jax.train import get_trainer, resolve_config

    cfg = resolve_config(env, algo, "smoke")
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps(config_document(cfg, ["test"])))
    trainer = get_trainer(cfg)
    state = trainer.init(jnp.asarray(cfg.seed, jnp.int32), jnp.arange(1, dtype=jnp.int32))
    save_checkpoint(folder / "checkpoints" / "group_0", 0, state, {"next_chunk": 0, "seeds": [0], "step": 0})
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


def test_baseline_shows_only_its_distribution_and_says_so(cli, tmp_path, capsys):
    run = make_run_folder(tmp_path / "dsac", "tracking", "dsac")
    status, _, err = call(cli, capsys, "--run", run, "--out", tmp_path / "b.png", *SMALL)
    assert status == 0, err
    assert "baseline without per-object explanations" in err
    rows = read_lines(tmp_path / "b.attributions.jsonl")
    assert rows and all(not r["explained"] and r["objects"] == [] for r in rows)


def one_line_error(status, err, *fragments):
    assert status == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


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
    multi = tmp_path / "multi"
    multi.mkdir()
    (multi / "config.json").write_text(json.dumps({"config": {"env": "intersection"}}))
    one_line_error(
        *call(cli, capsys, "--run", multi, "--out", png)[::2], "intersection runs are not supported"
    )
    assert not png.exists()


@pytest.mark.slow
def test_cli_on_a_trained_smoke_run(cli, tmp_path, capsys):
    run = load_script("run")
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
