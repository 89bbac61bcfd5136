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
