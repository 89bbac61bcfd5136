"""``bench.py compare`` and xrl_jax.benchmarks.compare: the round order, the ratio statistics, reading
``bench.py train``'s report, and the whole comparison on tiny git repositories whose experiments/bench.py
is a stand-in that prints a fixed rate at once (so no test trains but the one marked slow), including
every way it refuses or fails, each leaving no checkout behind."""

import itertools
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from train_support import call, load_script, one_line_error

from xrl_jax.benchmarks import compare as C

ROOT = Path(__file__).resolve().parents[1]

# A stand-in for experiments/bench.py: `train` prints one row per --seeds value at RATE × seeds.
FAKE_BENCH = """
import argparse, json, sys
RATE = @RATE@

def build_parser():
    parser = argparse.ArgumentParser(prog="bench.py")
    sub = parser.add_subparsers(dest="command", required=True)
    train = sub.add_parser("@COMMAND@")
    train.add_argument("--seeds", nargs="+", type=int, default=[1])
    @DEVICES@
    return parser

def main(argv=None):
    args = build_parser().parse_args(argv)
    @BODY@
    rows = [{"env": "tracking", "algo": "xsac", "width": 16, "seeds": s, "devices": 1, "num_envs": 4,
             "batch_size": @BATCH@, "env_steps_per_s": RATE * s} for s in args.seeds]
    print("a line of chatter before the report")
    print(json.dumps({"machine": {"backend": "fake"}, "command": "train", "results": rows}, indent=2))
    return 0

if __name__ == "__main__":
    sys.exit(main())
"""
DEVICES = 'train.add_argument("--devices", nargs="+", type=int, default=[1])'


def fake_bench(rate=100.0, command="train", devices=True, body="", batch=16, old_style=False) -> str:
    text = (
        FAKE_BENCH.replace("@RATE@", repr(rate))
        .replace("@COMMAND@", command)
        .replace("@DEVICES@", DEVICES if devices else "")
        .replace("@BODY@", body)
        .replace("@BATCH@", str(batch))
    )
    if old_style:  # as bench.py was before build_parser: the parser is built inside main
        text = text.replace("def build_parser():", "def _parser():").replace("build_parser()", "_parser()")
    return text


def git(repo: Path, *args: str) -> str:
    command = [
        "git",
        "-C",
        str(repo),
        "-c",
        "user.name=t",
        "-c",
        "user.email=t@t",
        "-c",
        "commit.gpgsign=false",
    ]
    return subprocess.run([*command, *args], check=True, capture_output=True, text=True).stdout.strip()


def write_bench(tree: Path, text: str) -> None:
    (tree / "experiments").mkdir(parents=True, exist_ok=True)
    (tree / "experiments" / "bench.py").write_text(text, encoding="utf-8")


@pytest.fixture
def scratch(tmp_path, monkeypatch):
    """Where the checkouts go (tempfile's folder), to see that none is left behind."""
    folder = tmp_path / "scratch"
    folder.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(folder))
    return folder


def make_repo(path: Path, rev_bench: str | None, tree_bench: str | None = None, sub: str = "") -> Path:
    """A repository whose one commit has ``rev_bench`` as ``sub``/experiments/bench.py (none: a text file
    alone); the working tree then holds ``tree_bench`` (uncommitted). Returns the project's root."""
    root = path / "repo" / sub
    root.mkdir(parents=True)
    git(path / "repo", "init", "-q")
    (root / "notes.txt").write_text("a project\n", encoding="utf-8")
    if rev_bench is not None:
        write_bench(root, rev_bench)
    git(path / "repo", "add", "-A")
    git(path / "repo", "commit", "-qm", "REV")
    if tree_bench is not None:
        write_bench(root, tree_bench)
    return root


def assert_cleaned_up(root: Path, scratch: Path) -> None:
    worktrees = [
        line
        for line in git(root, "worktree", "list", "--porcelain").splitlines()
        if line.startswith("worktree ")
    ]
    assert len(worktrees) == 1, worktrees
    assert not any(scratch.iterdir()), list(scratch.iterdir())


# The pure parts.


def test_the_order_alternates_each_round_so_each_side_leads_half_the_rounds():
    assert C.round_order(4) == [("tree", "rev"), ("rev", "tree"), ("tree", "rev"), ("rev", "tree")]
    assert C.round_order(1) == [("tree", "rev")]
    for rounds in range(1, 8):
        firsts = [pair[0] for pair in C.round_order(rounds)]
        assert firsts.count("tree") == (rounds + 1) // 2 and all(
            set(p) == {"tree", "rev"} for p in C.round_order(rounds)
        )


def test_options_are_rendered_as_argparse_read_them():
    words = C.render_options([("--seeds", [1, 5]), ("--set", []), ("--chunks", 2), ("--preset", "smoke")])
    assert words == ["--seeds", "1", "5", "--set", "--chunks", "2", "--preset", "smoke"]


def test_ratios_pair_the_rounds_and_their_median_min_and_max():
    stats = C.ratio_statistics([200.0, 300.0, 100.0], [100.0, 100.0, 100.0])
    assert stats["ratios"] == [2.0, 3.0, 1.0]
    assert (stats["median_ratio"], stats["min_ratio"], stats["max_ratio"]) == (2.0, 1.0, 3.0)
    assert stats["interval"] == {"low": 1.0, "high": 3.0, "confidence": 0.75}  # 1 - 2/8: exact in binary


def sign_test_coverage(n: int, k: int) -> float:
    """By enumeration: of the 2^n equally likely above/below-the-median patterns of n draws, the share
    where the k-th smallest draw is below the median and the k-th largest above it."""
    hits = sum(sum(signs) >= k and n - sum(signs) >= k for signs in itertools.product([0, 1], repeat=n))
    return hits / 2**n


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 8, 9, 12])
def test_the_median_interval_is_the_narrowest_order_statistics_interval_with_the_confidence(n):
    values = [float(v) for v in range(n, 0, -1)]  # given unsorted
    interval = C.median_interval(values, confidence=0.9)
    k = int(interval["low"])  # the value i is the i-th smallest
    assert interval["high"] == n + 1 - k and interval["confidence"] == sign_test_coverage(n, k)
    narrower_ok = k + 1 <= (n + 1) // 2 and sign_test_coverage(n, k + 1) >= 0.9
    assert not narrower_ok
    assert interval["confidence"] >= 0.9 or k == 1  # too few rounds: min-max, with what it has


def test_the_report_is_found_after_other_output_and_rows_are_named_by_their_loop_variables():
    rows = [
        {"env": "tracking", "algo": "xsac", "width": 16, "seeds": 5, "env_steps_per_s": 7.5}
    ]  # no devices
    text = "chatter\n{not json\n" + json.dumps({"machine": {"backend": "cpu"}, "results": rows}, indent=2)
    report = C.parse_train_report(text + "\n")
    assert report["machine"] == {"backend": "cpu"}
    assert report["rows"] == {("tracking", "xsac", 16, 5, 0): rows[0] | {"devices": 1}}  # one device then
    # Several --devices values time one configuration in turn: the rows are told apart by rank, and
    # the devices are work that a report shows where the sides differ.
    twice = [rows[0] | {"devices": 1}, rows[0] | {"devices": 2, "env_steps_per_s": 9.0}]
    keyed = C.parse_train_report(json.dumps({"results": twice}))["rows"]
    assert list(keyed) == [("tracking", "xsac", 16, 5, 0), ("tracking", "xsac", 16, 5, 1)]
    assert keyed[("tracking", "xsac", 16, 5, 1)]["devices"] == 2 and "devices" in C.WORK_FIELDS


@pytest.mark.parametrize(
    "text", ["", "Traceback ...", json.dumps({"results": [{"env": "tracking"}]}), json.dumps({"results": []})]
)
def test_output_without_a_train_report_is_refused(text):
    with pytest.raises(C.CompareError, match="no JSON report with env_steps_per_s") as err:
        C.parse_train_report(text)
    assert err.value.status == 1


def test_a_childs_last_lines_are_quoted_on_one_line():
    assert C.last_lines("a\n\nb\nc\n  d  \n") == "b | c | d"
    assert C.last_lines("") == "(nothing on standard error)"


def test_the_rows_of_bench_train_carry_what_compare_reads():
    """The cheap guard of the interface (the real run is the slow test below): bench_train's report
    names every field compare pairs rows by, reads and shows."""
    import inspect

    from xrl_jax.benchmarks import updates

    source = inspect.getsource(updates.bench_train)
    assert all(f'"{field}":' in source for field in (*C.KEY_FIELDS, *C.WORK_FIELDS, "env_steps_per_s"))


@pytest.mark.parametrize(
    "imports",
    ["import xrl_jax.benchmarks.compare",
     f"sys.path.insert(0, {str(ROOT / 'experiments')!r}); import bench"],  # bench.py compare's parent
)  # fmt: skip
def test_the_orchestration_imports_no_jax(imports):
    code = f"import sys; {imports}; assert 'jax' not in sys.modules, 'jax imported'"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr


# The whole comparison on tiny repositories.


def test_compare_times_both_trees_in_turn_and_reports_the_ratios(tmp_path, scratch):
    root = make_repo(tmp_path, fake_bench(rate=100.0), fake_bench(rate=250.0))
    lines = []
    report = C.compare(root, "HEAD", 3, ["--seeds", "1", "4"], lines.append)
    assert lines == [
        "round 1/3: the working tree", f"round 1/3: --against HEAD ({report['rev']['sha'][:12]})",
        f"round 2/3: --against HEAD ({report['rev']['sha'][:12]})", "round 2/3: the working tree",
        "round 3/3: the working tree", f"round 3/3: --against HEAD ({report['rev']['sha'][:12]})",
    ]  # fmt: skip
    assert report["rev"] == {"against": "HEAD", "sha": git(root, "rev-parse", "HEAD")}
    assert report["tree"] == {"path": str(root.resolve()), "head": report["rev"]["sha"], "dirty": True}
    assert report["machine"] == {"backend": "fake"} and report["order"][1] == ["rev", "tree"]
    assert [
        (row["seeds"], row["tree_env_steps_per_s"], row["rev_env_steps_per_s"]) for row in report["results"]
    ] == [
        (1, [250.0] * 3, [100.0] * 3),
        (4, [1000.0] * 3, [400.0] * 3),
    ]
    for row in report["results"]:
        assert (
            row["ratios"] == [2.5] * 3 and row["median_ratio"] == 2.5 and "work_differs_tree_rev" not in row
        )
    assert_cleaned_up(root, scratch)


def test_a_project_in_a_subfolder_of_its_repository_compares_the_same_subfolder(tmp_path, scratch):
    root = make_repo(tmp_path, fake_bench(rate=100.0), sub="project")
    report = C.compare(root, "HEAD", 1, [])
    assert report["results"][0]["ratios"] == [1.0] and report["tree"]["dirty"] is False
    assert_cleaned_up(root, scratch)


def test_different_work_per_step_is_shown_beside_the_ratio(tmp_path, scratch):
    root = make_repo(tmp_path, fake_bench(batch=16), fake_bench(batch=32))
    row = C.compare(root, "HEAD", 1, [])["results"][0]
    assert row["work_differs_tree_rev"] == {"batch_size": [32, 16]}


def test_sides_that_timed_different_configurations_stop_after_the_first_round(tmp_path, scratch):
    other_width = fake_bench().replace('"width": 16', '"width": 32')
    root = make_repo(tmp_path, other_width, fake_bench())
    lines = []
    with pytest.raises(
        C.CompareError, match=r"different configurations .*'tracking', 'xsac', 16, 1, 0\)"
    ) as err:
        C.compare(root, "HEAD", 3, [], lines.append)
    assert err.value.status == 1 and len(lines) == 2
    assert_cleaned_up(root, scratch)


def test_an_older_bench_py_without_build_parser_is_compared_too(tmp_path, scratch):
    root = make_repo(tmp_path, fake_bench(rate=50.0, old_style=True), fake_bench(rate=100.0))
    assert C.compare(root, "HEAD", 1, [])["results"][0]["ratios"] == [2.0]


@pytest.mark.parametrize(
    "rev_bench, args, fragments",
    [
        (None, [], ["--against HEAD: its tree has no experiments/bench.py"]),
        (
            fake_bench(command="env"),
            [],
            ["--against HEAD (", "has no train sub-command", "invalid choice: 'train'"],
        ),
        (fake_bench(devices=False), ["--devices", "1"], ["--against HEAD (", "rejects", "--devices"]),
        (
            fake_bench(devices=False, old_style=True),
            ["--devices", "1"],
            ["rejects", "unrecognized arguments: --devices 1"],
        ),
    ],
)
def test_a_rev_that_cannot_run_the_request_is_refused_before_any_run(
    tmp_path, scratch, rev_bench, args, fragments
):
    root = make_repo(tmp_path, rev_bench, fake_bench())
    lines = []
    with pytest.raises(C.CompareError) as err:
        C.compare(root, "HEAD", 3, args, lines.append)
    assert err.value.status == 2 and lines == []
    assert all(fragment in str(err.value) for fragment in fragments), str(err.value)
    assert "\n" not in str(err.value)
    assert_cleaned_up(root, scratch)


def test_a_rev_that_names_no_commit_is_refused(tmp_path, scratch):
    root = make_repo(tmp_path, fake_bench())
    with pytest.raises(C.CompareError, match=r"^--against no-such-rev: not a commit of this repository$"):
        C.compare(root, "no-such-rev", 1, [])
    assert_cleaned_up(root, scratch)


def test_outside_a_git_repository_compare_is_refused(tmp_path, scratch):
    write_bench(tmp_path / "plain", fake_bench())
    with pytest.raises(C.CompareError, match="is not in a git repository") as err:
        C.compare(tmp_path / "plain", "HEAD", 1, [])
    assert err.value.status == 2 and not any(scratch.iterdir())


@pytest.mark.parametrize("failing", ["tree", "rev"])
def test_a_failing_run_stops_all_quoting_its_last_lines_and_leaves_no_checkout(tmp_path, scratch, failing):
    boom = 'print("Traceback (most recent call last):", file=sys.stderr); raise ValueError("boom")'
    benches = {"tree": fake_bench(), "rev": fake_bench()}
    benches[failing] = fake_bench(body=boom)
    root = make_repo(tmp_path, benches["rev"], benches["tree"])
    lines = []
    with pytest.raises(C.CompareError) as err:
        C.compare(root, "HEAD", 3, [], lines.append)
    message = str(err.value)
    assert err.value.status == 1 and "\n" not in message, message
    assert "bench.py train failed (exit status 1)" in message and message.endswith("ValueError: boom"), (
        message
    )
    assert message.startswith("the working tree:" if failing == "tree" else "--against HEAD (")
    assert len(lines) == (1 if failing == "tree" else 2)  # it stopped at the first failure
    assert_cleaned_up(root, scratch)


def test_imports_from_outside_the_tree_are_refused(tmp_path, scratch):
    elsewhere = tmp_path / "elsewhere" / "helpers"
    elsewhere.mkdir(parents=True)
    (elsewhere / "__init__.py").write_text("", encoding="utf-8")
    shadowed = f"sys.path.insert(0, {str(elsewhere.parent)!r}); import helpers\n"
    root = make_repo(tmp_path, fake_bench().replace("RATE = ", shadowed + "RATE = "), fake_bench())
    (root / "helpers").mkdir()  # the tree's own package of that name, which the script's path hack shadows
    (root / "helpers" / "__init__.py").write_text("", encoding="utf-8")
    git(root, "add", "helpers")  # the working tree's bench.py stays as it is: uncommitted
    git(root, "commit", "-qm", "helpers")
    with pytest.raises(C.CompareError, match=r"would import helpers from .*elsewhere.*, outside its tree"):
        C.compare(root, "HEAD", 1, [])
    assert_cleaned_up(root, scratch)


def test_a_ctrl_c_leaves_no_checkout(tmp_path, scratch):
    root = make_repo(tmp_path, fake_bench(), fake_bench())

    def interrupt_at_the_second_run(line):
        if "--against" in line:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        C.compare(root, "HEAD", 2, [], interrupt_at_the_second_run)
    assert_cleaned_up(root, scratch)


# bench.py compare's command line.


@pytest.fixture(scope="module")
def bench():
    return load_script("bench", "bench_compare_cli")


@pytest.mark.parametrize(
    "args, message",
    [
        (["compare", "--seeds", "1"], "the following arguments are required: --against"),
        (["compare", "--against", "HEAD", "--rounds", "0"], "--rounds: expected a positive integer, got 0"),
        (
            ["compare", "--against", "HEAD", "--seeds", "3", "--devices", "2"],
            "every --seeds value must be a multiple",
        ),
        (["compare", "--against", "HEAD", "--algos", "ppo"], "--algos: invalid choice: 'ppo'"),
    ],
)
def test_bench_compare_refuses_bad_input_in_one_line(bench, capsys, args, message):
    status, _, err = call(bench, capsys, *args)
    one_line_error(status, err, message)


def test_bench_compare_passes_on_the_train_options_given_and_only_those(bench):
    parser = bench.build_parser()
    args = parser.parse_args(
        ["compare", "--against", "X", "--seeds", "1", "--set", "a=1", "b=2", "--rounds", "2"]
    )
    assert (args.against, args.rounds) == ("X", 2)
    assert bench.train_options(args) == ["--seeds", "1", "--set", "a=1", "b=2"]
    assert bench.train_options(parser.parse_args(["compare", "--against", "X"])) == []


@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(), reason="not a git checkout")
def test_bench_compare_names_a_rev_that_is_no_commit(bench, capsys):
    status, _, err = call(bench, capsys, "compare", "--against", "no-such-rev-of-xrl-jax")
    one_line_error(
        status, err, "bench.py: error: --against no-such-rev-of-xrl-jax: not a commit of this repository"
    )


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(), reason="not a git checkout")
def test_bench_compare_runs_the_real_train_against_head():
    """The one real run: a smoke configuration in both trees (about 45 s on 2 cores)."""
    args = ["--against", "HEAD", "--rounds", "1", "--preset", "smoke", "--chunks", "1", "--seeds", "1"]
    args += [
        "--widths",
        "16",
        "--algos",
        "xsac",
        "--set",
        "log_interval=64",
        "warmup_steps=32",
        "eval_episodes=1",
    ]
    done = subprocess.run(
        [sys.executable, "experiments/bench.py", "compare", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    (row,) = report["results"]
    assert (row["algo"], row["width"], row["seeds"]) == ("xsac", 16, 1)
    assert (
        row["tree_env_steps_per_s"][0] > 0 and row["rev_env_steps_per_s"][0] > 0 and len(row["ratios"]) == 1
    )
    assert report["rev"]["sha"] == report["tree"]["head"]
