"""The packages install, expose a version, and the CLI entry point answers --help."""

import re
import subprocess
import sys
from pathlib import Path

import envs
import xrl_jax

ROOT = Path(__file__).resolve().parents[1]
SEMVER = re.compile(r"^\d+\.\d+\.\d+")


def test_versions_are_exposed():
    assert SEMVER.match(xrl_jax.__version__)
    assert SEMVER.match(envs.__version__)


def test_envs_does_not_depend_on_xrl_jax():
    for path in (ROOT / "envs").rglob("*.py"):
        text = path.read_text()
        assert "import xrl_jax" not in text and "from xrl_jax" not in text, path


def test_envs_modules_are_small_and_import_no_private_names():
    """One home per fact: no module of envs/ over 600 lines, none importing another's private names."""
    private_import = re.compile(r"^\s*from envs[.\w]* import (?:\(([^)]*)\)|([^\n]*))", re.M)
    for path in sorted((ROOT / "envs").glob("*.py")):
        text = path.read_text()
        assert text.count("\n") <= 600, f"{path.name}: {text.count(chr(10))} lines"
        for match in private_import.finditer(text):
            imported = match.group(1) or match.group(2)
            names = [n.strip().split(" as ")[0] for n in re.sub(r"#[^\n]*", "", imported).split(",")]
            assert not [n for n in names if n.startswith("_") and n != "__future__"], (path.name, names)


def run_cli(*args):
    return subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "run.py"), *args],
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_run_help_exits_zero():
    result = run_cli("--help")
    assert result.returncode == 0, result.stderr
    for option in ("--env", "--algo", "--seeds", "--steps", "--preset", "--set", "--out", "--resume"):
        assert option in result.stdout


def test_run_rejects_unknown_env_in_one_line():
    result = run_cli("--env", "moon")
    assert result.returncode == 2
    assert "invalid choice: 'moon'" in result.stderr
    assert "tracking" in result.stderr


def test_run_rejects_non_positive_seeds():
    result = run_cli("--seeds", "0")
    assert result.returncode == 2
    assert "positive integer" in result.stderr


def test_the_library_and_the_trainer_run_without_the_optional_distrax():
    """distrax (and the TFP nightly it pulls) is an extra: only the distrax adaptors import it."""
    code = (
        "import sys; import xrl_jax.distributions, xrl_jax.agents, xrl_jax.train, envs; "
        "assert 'distrax' not in sys.modules and 'tensorflow_probability' not in sys.modules, 'imported'"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr


def test_the_config_and_the_cli_help_need_no_jax():
    code = "import sys; import xrl_jax.config; assert 'jax' not in sys.modules, 'jax imported'"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr


def test_envs_gymnax_without_the_extra_says_how_to_install_it(monkeypatch):
    """Without gymnax, ``import envs.gymnax`` names the extra to install (simulated: gymnax hidden)."""
    import importlib

    import pytest

    for name in [m for m in sys.modules if m == "gymnax" or m.startswith("gymnax.") or m == "envs.gymnax"]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "gymnax", None)  # import gymnax now fails as if not installed
    with pytest.raises(ModuleNotFoundError, match=r"pip install 'xrl-jax\[gymnax\]'") as error:
        importlib.import_module("envs.gymnax")
    assert "\n" not in str(error.value)
