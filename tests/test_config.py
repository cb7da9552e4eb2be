"""Config validation: schemas, units, file checks, and the messages users see."""

import math

import pytest
import yaml

from pipeline.config import (
    ConfigError,
    discover_tips,
    h_grid,
    load_tip_config,
    load_workflow_config,
    reduced_modulus,
)
from pipeline.units import QuantityError, parse_quantity


def write_tip(tmp_path, **overrides):
    data_dir = tmp_path / "scans"
    (data_dir / "curves" / "i0").mkdir(parents=True)
    (data_dir / "curves" / "i1").mkdir(parents=True)
    (data_dir / "curves" / "i0" / "c1.csv").write_text("x")
    (data_dir / "curves" / "i1" / "c1.csv").write_text("x")
    (data_dir / "i0.tif").write_bytes(b"x")
    (data_dir / "i1.tif").write_bytes(b"x")
    tip = {
        "data_dir": str(data_dir),
        "materials": {"tip": {"E": "150 GPa", "nu": 0.3}, "sample": {"E": "150 GPa", "nu": 0.3}},
        "cantilever": {"spring_constant": "0.2 N/m", "deflection_sensitivity": "50 nm/V"},
        "tem": {"pixel_size": "2.5 A"},
        "intervals": [
            {"name": "i0", "scans": 0, "image": "i0.tif", "curves": "curves/i0"},
            {"name": "i1", "scans": 10, "image": "i1.tif", "curves": "curves/i1"},
        ],
        "reference_intervals": ["i0"],
    }
    for key, value in overrides.items():
        node = tip
        parts = key.split(".")
        for p in parts[:-1]:
            node = node[int(p)] if p.isdigit() else node[p]
        if value is KeyError:
            del node[parts[-1]]
        else:
            node[parts[-1]] = value
    path = tmp_path / "tipX.yaml"
    path.write_text(yaml.safe_dump(tip))
    return path


def test_valid_tip_is_converted_to_si(tmp_path):
    tip = load_tip_config(write_tip(tmp_path))
    assert tip["name"] == "tipX"
    assert tip["cantilever"]["spring_constant"] == pytest.approx(0.2)
    assert tip["cantilever"]["deflection_sensitivity"] == pytest.approx(50e-9)
    assert tip["tem"]["pixel_size"] == pytest.approx(2.5e-10)  # Angstrom written "A"
    assert tip["tem"]["fit_height"] == pytest.approx(6e-9)  # schema default
    assert tip["tem"]["coating"] == "auto"
    # Eq. 7 with E = 150 GPa, nu = 0.3 on both sides: E* = E / (2 (1 - nu^2)) = 82.42 GPa
    assert tip["materials"]["E_star"] == pytest.approx(150e9 / (2 * 0.91), rel=1e-12)
    assert [iv["reference"] for iv in tip["intervals"]] == [True, False]
    assert tip["intervals"][1]["curve_paths"][0].name == "c1.csv"


def test_reduced_modulus_rigid_flat_limit():
    # a very stiff sample: E* -> E / (1 - nu^2) = 164.8 GPa (the paper's FE value)
    assert reduced_modulus(150e9, 0.3, 1e30, 0.3) == pytest.approx(164.835e9, rel=1e-4)


@pytest.mark.parametrize(
    "override, needle",
    [
        ({"cantilever.spring_constant": 0.2}, "cantilever.spring_constant: 0.2 has no unit"),
        ({"tem.pixel_size": "0.3 GPa"}, "tem.pixel_size: '0.3 GPa' is not a length"),
        ({"materials.tip.E": "150"}, "materials.tip.E"),
        ({"tem.colour": "red"}, "'colour' was unexpected"),
        (
            {
                "cantilever": {
                    "spring_constant": "0.2 N/m",
                    "deflection_sensitivity": "50 nm/V",
                    "springconstant": "1 N/m",
                }
            },
            "springconstant",
        ),
        ({"intervals.1.image": "missing.tif"}, "intervals[1].image"),
        ({"intervals.1.curves": "nothing_here"}, "intervals[1].curves"),
        ({"reference_intervals": ["nope"]}, "reference_intervals[0]"),
        ({"data_dir": KeyError}, "'data_dir' is a required property"),
        (
            {"materials": {"E_star": "80 GPa", "tip": {"E": "1 GPa", "nu": 0.3}}},
            "give either E_star, or both tip and sample",
        ),
        ({"tem.orientation": "sideways"}, "tem.orientation: 'sideways' is not one of"),
        ({"tem.coating": 15}, "tem.coating: 15 is not valid; expected 'auto' / 'none' or a length with its unit"),
        # values the types allow but physics does not (issue 17): named with file and key, not a traceback later
        ({"materials.tip.E": "-150 GPa"}, "materials.tip.E: must be positive"),
        ({"materials.tip.E": "0 GPa"}, "materials.tip.E: must be positive"),
        ({"materials.sample.nu": -1}, "materials.sample.nu: Poisson's ratio must lie in (-1, 0.5]"),
        (
            {"materials": {"E_star": "80 GPa", "E_star_uncertainty": "90 GPa"}},
            "E_star_uncertainty (90 GPa) is not smaller than E* (80 GPa)",
        ),
        (
            {"materials": {"E_star": "80 GPa", "E_star_uncertainty": "-1 GPa"}},
            "materials.E_star_uncertainty: an uncertainty must be >= 0",
        ),
        ({"cantilever.spring_constant": "0 N/m"}, "cantilever.spring_constant: must be positive"),
        ({"cantilever.deflection_sensitivity": "-50 nm/V"}, "cantilever.deflection_sensitivity: must be positive"),
        ({"tem.pixel_size": "0 nm"}, "tem.pixel_size: must be positive"),
        ({"tem.profile_height": "4 nm"}, "tem.profile_height (4 nm) is below tem.fit_height (6 nm)"),
    ],
)
def test_bad_tip_names_file_and_key(tmp_path, override, needle):
    path = write_tip(tmp_path, **override)
    with pytest.raises(ConfigError) as exc:
        load_tip_config(path)
    msg = str(exc.value)
    assert str(path) in msg
    assert needle in msg


def test_tip_without_tem_section_gets_converted_defaults(tmp_path):
    tip = load_tip_config(write_tip(tmp_path, tem=KeyError))
    assert tip["tem"]["fit_height"] == pytest.approx(6e-9) and tip["tem"]["profile_height"] == pytest.approx(20e-9)


def test_non_utf8_yaml_is_one_line(tmp_path):
    path = write_tip(tmp_path)
    path.write_bytes(path.read_bytes().replace(b"50 nm/V", b"0.05 \xb5m/V"))  # a Latin-1 micro sign
    with pytest.raises(ConfigError, match=r"tipX.yaml: line \d+: byte 0xb5 is not UTF-8.*save the file as UTF-8"):
        load_tip_config(path)


def test_all_reference_is_rejected(tmp_path):
    with pytest.raises(ConfigError, match="at least one worn interval"):
        load_tip_config(write_tip(tmp_path, reference_intervals=["i0", "i1"]))


def test_workflow_defaults_and_grid(tmp_path):
    cfg = load_workflow_config({"tips_dir": str(tmp_path), "results_dir": "r"})
    grid = h_grid(cfg)
    assert len(grid) == 200
    assert grid[0] == pytest.approx(0.2e-9) and grid[-1] == pytest.approx(10e-9)
    assert math.isclose(grid[1] / grid[0], grid[-1] / grid[-2], rel_tol=1e-9)
    assert cfg["solver_mode"] == "auto" and cfg["traction_laws"] == ["dugdale", "lj", "tri1", "tri2"]


def test_workflow_errors(tmp_path):
    with pytest.raises(ConfigError, match="h_grid.min: 0.2 has no unit"):
        load_workflow_config({"tips_dir": "x", "results_dir": "r", "h_grid": {"min": 0.2}})
    with pytest.raises(ConfigError, match="need 0 < min < max"):
        load_workflow_config({"tips_dir": "x", "results_dir": "r", "h_grid": {"min": "5 nm", "max": "1 nm"}})
    with pytest.raises(ConfigError, match="solver_mode: 'fast' is not one of"):
        load_workflow_config({"tips_dir": "x", "results_dir": "r", "solver_mode": "fast"})
    load_workflow_config({"tips_dir": "x", "results_dir": "r", "monte_carlo": {"samples": 100000}})
    with pytest.raises(ConfigError, match="monte_carlo.samples: 100001 is greater than the maximum of 100000"):
        load_workflow_config({"tips_dir": "x", "results_dir": "r", "monte_carlo": {"samples": 100001}})
    (tmp_path / "afile").write_text("x")
    with pytest.raises(ConfigError, match="results_dir: .*afile' is an existing file, not a folder"):
        load_workflow_config({"tips_dir": "x", "results_dir": str(tmp_path / "afile")})


def test_discover_tips(tmp_path):
    (tmp_path / "a.yaml").write_text("{}")
    (tmp_path / "b.yaml").write_text("{}")
    cfg = {"tips_dir": str(tmp_path)}
    assert list(discover_tips(cfg)) == ["a", "b"]
    assert list(discover_tips({**cfg, "tips": ["b"]})) == ["b"]
    with pytest.raises(ConfigError, match="no YAML for"):
        discover_tips({**cfg, "tips": ["c"]})


@pytest.mark.parametrize(
    "text, kind, si",
    [
        ("150 GPa", "pressure", 150e9),
        ("0.3 nm", "length", 0.3e-9),
        ("3 A", "length", 3e-10),
        ("3 Å", "length", 3e-10),
        ("2 µm", "length", 2e-6),
        ("300 pm", "length", 3e-10),
        ("0.2 N/m", "stiffness", 0.2),
        ("46.7 mJ/m^2", "energy_per_area", 0.0467),
        ("44.99 nm/V", "sensitivity", 44.99e-9),
        ("90 deg", "angle", math.pi / 2),
        ("1e-3 m", "length", 1e-3),
    ],
)
def test_parse_quantity(text, kind, si):
    assert parse_quantity(text, kind) == pytest.approx(si, rel=1e-12)


def test_parse_quantity_rejects():
    with pytest.raises(QuantityError, match="bare number"):
        parse_quantity(5, "length")
    with pytest.raises(QuantityError, match="not a pressure"):
        parse_quantity("5 nm", "pressure")
    with pytest.raises(QuantityError, match="unknown unit"):
        parse_quantity("5 furlongz", "length")


def test_dat_curves_in_a_folder_are_listed(tmp_path):
    """Curves saved as .dat (read as CSV/white space) are found in an interval's folder."""
    path = write_tip(tmp_path)
    d = tmp_path / "scans" / "curves" / "i1"
    (d / "c1.csv").unlink()
    (d / "c2.dat").write_text("x")
    tip = load_tip_config(path)
    assert [p.name for p in tip["intervals"][1]["curve_paths"]] == ["c2.dat"]
