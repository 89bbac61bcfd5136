"""The checkpoints' config fingerprint (xrl_jax.train.restore.config_fingerprint) across upgrades:
a run written before a setting existed keeps its fingerprint, so it resumes and is read after the
upgrade; setting the new setting changes it."""

import json
from pathlib import Path

import pytest

from xrl_jax.config import TrainConfig
from xrl_jax.train.restore import LATE_AGENT_SETTINGS, LATE_TRAIN_SETTINGS, config_fingerprint

# tests/data/README.md §1: the config.json of a run whose checkpoints were written before the
# on-policy settings existed, and the fingerprint those checkpoints carry.
BEFORE_ON_POLICY = Path(__file__).parent / "data" / "config_before_on_policy.json"
ITS_FINGERPRINT = "857eca8013f85133"


def stored_config() -> TrainConfig:
    return TrainConfig.from_dict(json.loads(BEFORE_ON_POLICY.read_text()))


def test_a_run_written_before_a_setting_existed_keeps_its_fingerprint():
    """Fails when a setting is added to TrainConfig or AgentConfig without joining the late lists
    of xrl_jax.train.restore: every run started before the upgrade would then refuse --resume
    ("written by another configuration"), which is how this test came to be."""
    assert config_fingerprint(stored_config()) == ITS_FINGERPRINT


@pytest.mark.parametrize(
    "change",
    [
        {"agent": {"ppo_epochs": 8}},
        {"agent": {"gae_lambda": 0.9}},
        {"agent": {"value_clip_eps": 0.2}},
        {"sweep": (("gamma", (0.9, 0.95)),)},
    ],
)
def test_a_late_setting_away_from_its_default_changes_the_fingerprint(change):
    cfg = stored_config()
    if "agent" in change:
        cfg = cfg.replace(agent=cfg.agent.replace(**change["agent"]))
    else:
        cfg = cfg.replace(**change)
    assert config_fingerprint(cfg) != ITS_FINGERPRINT


def test_the_late_settings_are_settings():
    from xrl_jax.config import AgentConfig

    assert set(LATE_TRAIN_SETTINGS) <= set(TrainConfig.__dataclass_fields__)
    assert set(LATE_AGENT_SETTINGS) <= set(AgentConfig.__dataclass_fields__)
