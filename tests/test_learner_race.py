"""benchmarks/learner_race.py's learner specs: ``NAME:FIELD=VALUE,...`` -> an ``RLConfig``."""

import dataclasses
import importlib.util
from pathlib import Path

import pytest

from sparsecomm.configs import RLConfig

_spec = importlib.util.spec_from_file_location(
    "learner_race", Path(__file__).parents[1] / "benchmarks" / "learner_race.py"
)
race = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(race)


def test_a_spec_sets_its_fields_nested_ones_too_and_nothing_else():
    name, overrides = race.parse_learner(
        "fast:num_envs=16,lr_final=1e-4,lr_decay_steps=2000,agent.message_gate=hard"
    )
    assert name == "fast"
    assert overrides == {
        "num_envs": 16,
        "lr_final": 1e-4,
        "lr_decay_steps": 2000,
        "agent.message_gate": "hard",
    }
    config = race.make_config(overrides)
    default = RLConfig()
    agent = dataclasses.replace(default.agent, message_gate="hard")
    want = dataclasses.replace(
        default, num_envs=16, lr_final=1e-4, lr_decay_steps=2000, agent=agent
    )
    assert config == want
    assert race.make_config(race.parse_learner("today:")[1]) == default


def test_a_spec_with_a_bad_value_is_refused_by_the_config():
    with pytest.raises(ValueError, match="lr_decay_steps"):
        race.make_config(race.parse_learner("x:lr_final=1e-4")[1])
