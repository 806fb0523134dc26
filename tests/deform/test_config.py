"""Rod configs: shipped as package data, validated, unknown keys refused."""

import pytest

from deform.config import ROD_DIR, ConfigError, RodConfig, available_rods, load_rod_config


def test_every_shipped_rod_validates_and_is_found_by_name():
    assert available_rods() == ["DLO1", "DLO2", "DLO3", "DLO4", "DLO5"]
    assert ROD_DIR.parent.name == "deform"  # package data, not a path into a checkout's config/
    for rod in available_rods():
        cfg = load_rod_config(rod)
        assert isinstance(cfg, RodConfig) and cfg.name == rod


def test_bad_rod_files_name_file_and_field(tmp_path):
    with pytest.raises(ConfigError, match="unknown rod 'DLO9'"):
        load_rod_config("DLO9")
    bad = tmp_path / "r.yaml"
    bad.write_text(
        "name: x\nlength_m: 1\nmass_kg: 0.1\nn_vertices: 12\nbend_stiffness: 1e-3\ntwist_stiffness: 1e-3\nlenght: 2\n"
    )
    with pytest.raises(ConfigError, match=r"r\.yaml.*lenght"):
        load_rod_config(bad)
