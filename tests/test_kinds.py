"""The scenario kinds (xrl_jax.train.kinds): every scenario names a registered kind whose answers agree
with the configuration's facts, and outside the kinds' room the library branches on the kind in at
most MAX_KIND_BRANCHES places (issue 48: adding a kind is one module and one registry line)."""

import ast
from pathlib import Path

import pytest

from xrl_jax.config import ENVS, SCENARIOS, resolve_config, scenario
from xrl_jax.config.names import PRESETS
from xrl_jax.config.presets import TRAIN_PRESETS
from xrl_jax.train.kinds import KINDS, ScenarioKind, scenario_kind

ROOT = Path(__file__).resolve().parents[1]
ROOM = ("xrl_jax", "train", "kinds")
MAX_KIND_BRANCHES = 6
# What names a scenario kind outside the room: the scenario's kind-identifying facts, its kind, and
# the names of the kinds and the built-in scenarios compared against.
KIND_FACTS = {"multi_agent", "MULTI_AGENT_ENVS", "on_tracks", "custom", "fresh_tracks", "agent_slots"}
KIND_NAMES = {"racing", "multi_agent", "user_env", *ENVS}


def test_every_scenario_names_a_registered_kind():
    assert {facts.kind for facts in SCENARIOS.values()} <= set(KINDS)
    for name, kind in KINDS.items():
        assert isinstance(kind, ScenarioKind) and kind.name == name
    assert [scenario_kind(env).name for env in ENVS] == ["racing", "racing", "multi_agent"]
    cfg = resolve_config("intersection", "xdsac", "smoke")
    assert scenario_kind(cfg) is KINDS["multi_agent"]


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_every_preset_has_train_rows_for_every_kind(kind):
    for preset in PRESETS:
        assert (preset, kind) in TRAIN_PRESETS


def test_a_new_kind_is_one_class_and_one_registry_entry(monkeypatch):
    """docs/layout.md's recipe: a ScenarioKind subclass in KINDS, and a scenario naming it, which the
    presets serve with the single-agent rows until the kind has its own."""
    import dataclasses

    from xrl_jax.config.presets import preset_train_fields
    from xrl_jax.config.scenarios import register_scenario, unregister_scenario

    class Platoon(ScenarioKind):
        name = "platoon"
        figure = "slots"

    monkeypatch.setitem(KINDS, "platoon", Platoon())
    register_scenario(dataclasses.replace(scenario("tracking"), name="convoy", kind="platoon"))
    try:
        assert scenario_kind("convoy").name == "platoon"
        assert preset_train_fields("smoke", "convoy") == TRAIN_PRESETS[("smoke", "user_env")]
    finally:
        unregister_scenario("convoy")


@pytest.mark.parametrize("env", ENVS)
def test_the_kinds_answers_agree_with_the_scenarios_facts(env):
    """The config (below the trainer) reads the buffer layout and its size check off the scenario's
    agent slots, the kind builds the buffer and the actors: they must agree. The explanation figure a
    kind names exists."""
    from xrl_jax.explain.run_figures import FIGURES

    cfg = resolve_config(env, "xdsac", "smoke")
    kind, facts = scenario_kind(cfg), scenario(env)
    packed = kind.buffer_columns(cfg) == 1 and cfg.num_envs > 1
    assert packed == (facts.agent_slots > 1)
    assert cfg.buffer_layout == ("explicit" if packed else "compact")
    assert kind.slots_explained == (facts.agent_slots if facts.agent_slots > 1 else 0)
    assert kind.seeded_evaluation == (facts.agent_slots == 1)
    assert kind.figure in FIGURES


def _names_a_kind(node: ast.AST) -> bool:
    for sub in ast.walk(node):
        if isinstance(sub, ast.Attribute) and sub.attr in KIND_FACTS:
            return True
        if isinstance(sub, ast.Name) and sub.id in KIND_FACTS:
            return True
        owner = getattr(sub, "value", None)  # scenario(env).kind, cfg.scenario.kind
        if isinstance(sub, ast.Attribute) and sub.attr == "kind":
            if isinstance(owner, ast.Call) and getattr(owner.func, "id", "") == "scenario":
                return True
            if isinstance(owner, ast.Attribute) and owner.attr == "scenario":
                return True
        if isinstance(sub, ast.Compare):
            for operand in (sub.left, *sub.comparators):
                values = operand.elts if isinstance(operand, (ast.Tuple, ast.List, ast.Set)) else [operand]
                for value in values:
                    text = value.value if isinstance(value, ast.Constant) else None
                    if isinstance(text, str) and text.removesuffix("_discrete") in KIND_NAMES:
                        return True
    return False


def kind_branches() -> list[str]:
    """Lines of the library outside the kinds' room whose condition (if, conditional expression, a
    boolean operation or comparison) names a scenario kind."""
    found = set()
    for path in sorted((ROOT / "xrl_jax").rglob("*.py")):
        relative = path.relative_to(ROOT)
        if relative.parts[: len(ROOM)] == ROOM:
            continue
        source = path.read_text(encoding="utf-8")
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, (ast.If, ast.IfExp, ast.While)):
                tests = [node.test]
            elif isinstance(node, (ast.BoolOp, ast.Compare)):
                tests = [node]
            else:
                continue
            found.update(
                f"{relative}:{t.lineno}: {source.splitlines()[t.lineno - 1].strip()}"
                for t in tests
                if _names_a_kind(t)
            )
    return sorted(found)


def test_the_detector_sees_the_branches_it_counts():
    for source in (
        "if cfg.multi_agent: pass",
        "x = 1 if scenario(env).custom else 2",
        "if env == 'intersection': pass",
        "ok = cfg.fresh_tracks or not cfg.scenario.on_tracks",
        "if cfg.scenario.kind == k: pass",
        "if name in ('tracking', 'country_road'): pass",
    ):
        assert any(_names_a_kind(node) for node in ast.walk(ast.parse(source))), source
    for source in ("if step.kind == 'discrete': pass", "env = request.env or 'tracking'"):
        assert not any(
            _names_a_kind(node) for node in ast.walk(ast.parse(source)) if isinstance(node, ast.Compare)
        ), source


def test_outside_the_kinds_room_few_lines_branch_on_the_kind():
    """The trainer, evaluation, report, explanations and campaign ask the kind; what is left is the
    configuration's data (below the trainer, it cannot ask the kind) and the summary's training
    tracks (below the trainer too)."""
    branches = kind_branches()
    assert len(branches) <= MAX_KIND_BRANCHES, "\n".join(branches)


def test_outside_the_families_room_nothing_branches_on_the_family():
    """The trainer asks the run's algorithm family (xrl_jax.train.families); only the configuration,
    below it, and the agents' own constructors tell the families apart."""
    allowed = {"xrl_jax/train/families.py", "xrl_jax/ppo.py"}
    found = []
    for path in sorted((ROOT / "xrl_jax").rglob("*.py")):
        relative = path.relative_to(ROOT).as_posix()
        if relative in allowed or relative.startswith("xrl_jax/config/"):
            continue
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if "is_on_policy" in line or "ON_POLICY_ALGOS" in line:
                found.append(f"{relative}:{number}: {line.strip()}")
    assert not found, "\n".join(found)
