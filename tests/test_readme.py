"""The README's Python examples run as written, in order, in one namespace (as a reader pastes them)."""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1].joinpath("README").with_suffix(".md")  # the top-level one
BLOCK = re.compile(r"^```python\n(.*?)^```", re.MULTILINE | re.DOTALL)


def test_every_python_block_of_the_readme_runs_in_order():
    blocks = BLOCK.findall(README.read_text(encoding="utf-8"))
    assert len(blocks) >= 4  # environments, intersection, algorithms, explanations
    namespace: dict = {}
    for number, code in enumerate(blocks, 1):
        try:
            exec(compile(code, f"README python block {number}", "exec"), namespace)
        except Exception as err:  # name the block: a traceback into exec'd text is hard to place
            raise AssertionError(f"README python block {number} fails: {type(err).__name__}: {err}") from err
    explanation = namespace["explanation"]
    assert explanation.policy.component_probs().shape[-1] == 12
    assert float(namespace["removed"]) <= 0.05


SHELL_BLOCK = re.compile(r"^```bash\n(.*?)^```", re.MULTILINE | re.DOTALL)
INLINE_COMMAND = re.compile(r"`(python experiments/[^`]+)`")


def readme_commands() -> list[str]:
    """Every ``python experiments/...`` command the README shows, in shell blocks (continuation lines
    joined, ``&&`` chains split, ``srun`` dropped) or inline (across line breaks); synopses with
    ``{a,b}`` or ``[...]`` are not commands and are left out."""
    text = README.read_text(encoding="utf-8")
    lines = [line for block in SHELL_BLOCK.findall(text) for line in block.replace("\\\n", " ").splitlines()]
    pieces = [
        piece.strip() for line in lines if not line.lstrip().startswith("#") for piece in line.split("&&")
    ]
    pieces += INLINE_COMMAND.findall(text)
    commands = [" ".join(piece.removeprefix("srun ").split()) for piece in pieces]
    return [c for c in commands if c.startswith("python experiments/") and not re.search(r"[{\[]", c)]


def test_every_command_of_the_readme_parses(monkeypatch):
    """The arguments of each command the README shows are ones its script accepts (checked by the
    script's own parser after its ``--import`` modules, from the repository root as the README runs
    them; running them would train)."""
    import shlex

    from train_support import load_script

    monkeypatch.chdir(README.parent)
    commands = readme_commands()
    assert len(commands) >= 15
    for command in commands:
        words = shlex.split(command)
        name = words[1].removeprefix("experiments/").removesuffix(".py")
        script = load_script(name, f"{name}_for_readme")
        if hasattr(script, "import_user_modules"):  # e.g. the module that registers a user's env
            assert script.import_user_modules(words[2:]) is None, command
        parser = script.build_parser()
        try:
            parser.parse_args(words[2:])
        except SystemExit as exc:
            assert words[2:] == ["--help"] and exc.code == 0, f"README command does not parse: {command}"
