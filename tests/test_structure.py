"""The shape of the house (README, "Where things live"; docs/layout.md): every part of the library
imports only from the layers below it, no modules import each other in a circle, no module is over
450 lines, no class over 250 and no function over 120. The import graph is read from the source (``ast``),
function-level imports included, so a deferred import cannot hide an arrow back up. ``LAYERS`` is the one
list of the layers: the README and docs/layout.md state it, and a test checks that they state it."""

import ast
import re
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Bottom-up; a part may import from the layers before its own, never from its own layer or above.
LAYERS = [
    {"envs", "config"},
    {"stats", "sets", "trig", "checkpoint", "interrupts", "resources", "buffer", "tracks", "custom_envs"},
    {"distributions", "extractors"},
    {"losses", "actors", "critics"},
    {"action_spaces", "policies"},
    {"networks", "agent_state"},
    {"agents"},
    {"evaluation", "ppo"},
    {"runs"},  # the results folder: the trainer writes it
    {"train"},
    {"report_figures", "comparisons"},
    {"report", "explain", "benchmarks"},
    {"campaign"},
]
# What the README and docs/layout.md state: the library's layers, then the scripts of experiments/ on top.
STATED_LAYERS = [*LAYERS, {"experiments"}]
LAYER_OF = {part: index for index, layer in enumerate(LAYERS) for part in layer}
MAX_MODULE_LINES = 450
MAX_CLASS_LINES = 250
MAX_FUNCTION_LINES = 120


def source_files():
    return sorted([*(ROOT / "xrl_jax").rglob("*.py"), *(ROOT / "envs").rglob("*.py")])


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def part_of(module: str) -> str | None:
    """The layered part a module belongs to: ``envs`` or the first name below ``xrl_jax``."""
    names = module.split(".")
    if names[0] == "envs":
        return "envs"
    if names[0] == "xrl_jax" and len(names) > 1:
        return names[1]
    return None


def imports(path: Path, module_level_only: bool) -> set[str]:
    """The project modules ``path`` imports: ``from xrl_jax.train import hosts`` imports the module
    ``xrl_jax.train.hosts``, ``from xrl_jax.config import preset`` the module ``xrl_jax.config``."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = set()
    for node in tree.body if module_level_only else ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            for alias in node.names:
                submodule = f"{node.module}.{alias.name}"
                found.add(submodule if submodule in MODULES else node.module)
    return {name for name in found if name in MODULES}


MODULES = {module_name(path) for path in source_files()}


def test_every_part_of_the_library_has_a_layer():
    parts = {part_of(module_name(path)) for path in source_files()} - {None}
    assert parts == set(LAYER_OF), f"without a layer: {parts - set(LAYER_OF)}; gone: {set(LAYER_OF) - parts}"


def test_imports_only_point_down_the_layers():
    upward = []
    for path in source_files():
        own = part_of(module_name(path))
        if own is None:
            continue
        for target in imports(path, module_level_only=False):
            other = part_of(target)
            if other in LAYER_OF and other != own and LAYER_OF[other] >= LAYER_OF[own]:
                upward.append(f"{path.relative_to(ROOT)} imports {target}")
    assert not upward, "\n".join(upward)


def test_no_import_circle_between_modules():
    files = {module_name(path): path for path in source_files()}
    graph = defaultdict(set)
    for name, path in files.items():
        graph[name] = imports(path, module_level_only=True) - {name}
    done, on_path = set(), []

    def visit(module):
        if module in on_path:
            pytest.fail("import circle: " + " -> ".join([*on_path[on_path.index(module) :], module]))
        if module in done:
            return
        on_path.append(module)
        for target in sorted(graph[module]):
            visit(target)
        on_path.pop()
        done.add(module)

    for module in sorted(files):
        visit(module)


def test_modules_and_functions_stay_small():
    too_long = []
    for path in source_files():
        text = path.read_text(encoding="utf-8")
        if text.count("\n") > MAX_MODULE_LINES:
            too_long.append(f"{path.relative_to(ROOT)}: {text.count(chr(10))} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    too_long.append(f"{path.relative_to(ROOT)}: {node.name} is {length} lines")
    assert not too_long, "\n".join(too_long)


def test_classes_stay_small():
    too_long = []
    for path in source_files():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            length = node.end_lineno - node.lineno + 1 if isinstance(node, ast.ClassDef) else 0
            if length > MAX_CLASS_LINES:
                too_long.append(f"{path.relative_to(ROOT)}: class {node.name} is {length} lines")
    assert not too_long, "\n".join(too_long)


def stated_layers(text: str) -> list[set[str]]:
    """The layers a document states in its sentence "Layers, bottom-up ...: `a`, `b` < `c` < ...":
    the parts in backticks, ``<`` between layers, asides in parentheses skipped, up to the full stop."""
    sentence = re.search(r"Layers, bottom-up[^:]*:(.*?)\.(?:\s|$)", re.sub(r"\([^()]*\)", "", text), re.S)
    assert sentence, "no sentence 'Layers, bottom-up ...: `envs`, `config` < ...'"
    return [set(re.findall(r"`(\w+)`", layer)) for layer in re.split(r"\s<\s", sentence.group(1))]


@pytest.mark.parametrize("document", ["README", "docs/layout"])  # the top-level README
def test_the_docs_state_the_layers_of_this_test(document):
    """The layer order is written once, in LAYERS; the README and docs/layout.md must say the same."""
    stated = stated_layers(ROOT.joinpath(document).with_suffix(".md").read_text(encoding="utf-8"))
    assert stated == STATED_LAYERS, (
        "\n".join(
            f"layer {i}: {sorted(got)} stated, {sorted(want)} in LAYERS"
            for i, (got, want) in enumerate(zip(stated, STATED_LAYERS, strict=False))
            if got != want
        )
        or f"{len(stated)} layers stated, {len(STATED_LAYERS)} in LAYERS"
    )


def test_the_map_of_the_house_names_every_module():
    """docs/layout.md lists every module of the library and every experiment script, one line each."""
    layout = (ROOT / "docs" / "layout.md").read_text(encoding="utf-8")
    files = [*source_files(), *(ROOT / "experiments").glob("*.py")]
    missing = [str(path.relative_to(ROOT)) for path in files
               if path.name != "__init__.py" and f" {path.name} " not in layout]  # fmt: skip
    assert not missing, f"not in docs/layout.md: {missing}"
