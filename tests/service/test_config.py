"""The service config: the pydantic models are the one source of defaults, the shipped YAML lists them."""

from pathlib import Path

import pytest
import yaml

from service.config import ServiceConfig, ServiceConfigError, load_config

SHIPPED = Path(__file__).resolve().parents[2] / "config" / "service.yaml"


def _keys(d: dict, prefix: str = "") -> set[str]:
    out = set()
    for k, v in d.items():
        out.add(prefix + k)
        if isinstance(v, dict):
            out |= _keys(v, f"{prefix}{k}.")
    return out


def test_shipped_yaml_equals_the_defaults_and_lists_every_field():
    data = yaml.safe_load(SHIPPED.read_text())
    assert load_config(SHIPPED) == ServiceConfig() == load_config()
    assert _keys(data) == _keys(ServiceConfig().model_dump())


def test_unknown_keys_and_bad_values_name_the_file_and_field(tmp_path):
    bad = tmp_path / "s.yaml"
    bad.write_text("timeouts: {pose_s: 0.2, cloud_z: 1}\n")
    with pytest.raises(ServiceConfigError, match=r"s\.yaml.*cloud_z"):
        load_config(bad)
    bad.write_text("rate_hz: -1\n")
    with pytest.raises(ServiceConfigError, match="rate_hz"):
        load_config(bad)
    bad.write_text("workers: {predict_network_dtype: float16}\n")  # not a precision predict offers
    with pytest.raises(ServiceConfigError, match="predict_network_dtype"):
        load_config(bad)
    with pytest.raises(ServiceConfigError, match="no such file"):
        load_config(tmp_path / "missing.yaml")


def test_perception_settings_file_is_checked_at_load(tmp_path):
    good = tmp_path / "p.yaml"
    good.write_text("tracker: {stale_after_s: 0.5}\n")
    assert load_config(perception=str(good)).perception == str(good)
    bad = tmp_path / "q.yaml"
    bad.write_text("tracker: {stale_after: 0.5}\n")
    with pytest.raises(ServiceConfigError, match="stale_after"):
        load_config(perception=str(bad))


def test_rod_is_checked_at_load_not_in_a_started_worker(tmp_path):
    assert load_config(rod="DLO3").rod == "DLO3"
    model = tmp_path / "m.pt"
    model.write_bytes(b"")  # a file: its content is the loop's to read
    assert load_config(rod=str(model)).rod == str(model)
    with pytest.raises(ServiceConfigError, match="unknown rod 'DLO9'"):
        load_config(rod="DLO9")
    with pytest.raises(ServiceConfigError, match="no such model file"):
        load_config(rod=str(tmp_path / "gone.pt"))
