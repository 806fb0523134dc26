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


def test_generic_rod_from_length_and_mass():
    """Stiffness follows the linear density (heavier per metre: stiffer); no markers; bad input is
    a ConfigError naming the field."""
    from deform import ConfigError, generic_model, generic_rod
    from deform.config import BEND_PER_LINEAR_DENSITY, TWIST_OVER_BEND

    light, heavy = generic_rod(1.0, 0.02), generic_rod(1.0, 0.08)
    assert heavy.bend_stiffness == pytest.approx(4 * light.bend_stiffness)
    assert light.bend_stiffness == pytest.approx(BEND_PER_LINEAR_DENSITY * 0.02)
    assert light.twist_stiffness == pytest.approx(TWIST_OVER_BEND * light.bend_stiffness)
    assert light.marker_mass_kg == 0.0 and light.n_vertices == 12
    with pytest.raises(ConfigError, match="mass_kg"):
        generic_rod(1.0, 0.0)
    model = generic_model(0.8, 0.03, n_vertices=10)
    assert not model.options.residual and model.n == 10
    assert float(model.nominal_rest.sum()) == pytest.approx(0.8)


def test_the_stiffness_prior_leaves_out_the_rods_named():
    """The prior is the shipped rods' median EI L / m (the constant, rounded); a rod left out has no
    part in it; a rod built from another prior has EI = prior m / L."""
    from deform import ConfigError, available_rods, bend_per_linear_density, generic_rod
    from deform.config import BEND_PER_LINEAR_DENSITY

    assert bend_per_linear_density() == pytest.approx(BEND_PER_LINEAR_DENSITY, rel=0.01)
    without = {rod: bend_per_linear_density([rod]) for rod in available_rods()}
    own = {
        rod: (c := load_rod_config(rod)).bend_stiffness * c.length_m / c.mass_kg for rod in available_rods()
    }
    lowest = min(own, key=own.get)
    assert without[lowest] > bend_per_linear_density()  # the softest out: the median rises
    assert generic_rod(1.0, 0.05, prior=without["DLO3"]).bend_stiffness == pytest.approx(
        without["DLO3"] * 0.05
    )
    with pytest.raises(ConfigError, match="no shipped rod"):
        bend_per_linear_density(available_rods())
    with pytest.raises(ConfigError, match="prior"):
        generic_rod(1.0, 0.05, prior=0.0)


def test_rod_yaml_without_stiffness_takes_the_generic_guess(tmp_path):
    path = tmp_path / "cable.yaml"
    path.write_text("name: cable\nlength_m: 1.2\nmass_kg: 0.06\n")
    cfg = load_rod_config(path)
    assert cfg.bend_stiffness == pytest.approx(0.0124 * 0.05) and cfg.n_vertices == 12
    assert load_rod_config("DLO1").bend_stiffness == 0.0005  # given values are kept
