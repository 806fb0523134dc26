"""Perception settings: the dataclasses are the one source of defaults, the shipped YAML lists them."""

from dataclasses import asdict
from pathlib import Path

import pytest
import yaml

from perception import PerceptionConfig, load_config

SHIPPED = Path(__file__).resolve().parents[2] / "config" / "perception.yaml"


def test_shipped_yaml_equals_the_defaults_and_lists_every_key():
    assert load_config(SHIPPED) == PerceptionConfig() == load_config()
    data = yaml.safe_load(SHIPPED.read_text())
    defaults = asdict(PerceptionConfig())
    assert {s: set(v) for s, v in data.items()} == {s: set(v) for s, v in defaults.items()}


def test_unknown_keys_are_refused():
    with pytest.raises(ValueError, match="unknown keys"):
        load_config({"tracker": {"stale_after": 1.0}})
    with pytest.raises(ValueError, match="unknown sections"):
        load_config({"trackers": {}})
