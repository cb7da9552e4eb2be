"""The Cramér-Rao yardstick of the wave-optical grid (``pipeline.synth.tem_wave_bound``)."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.synth.tem_fisher import crb_summary, default_apex, fisher_information
from pipeline.synth.tem_truth import TIP_SHAPES
from pipeline.synth.tem_wave import TemWaveParams, simulate
from pipeline.synth.tem_wave_bound import twin_bound, vacuum_dose

CRB_GRID = __import__("pathlib").Path(__file__).parent / "data" / "crb_grid.csv"


@pytest.mark.parametrize("bits", [8, 16, 0])
def test_the_dose_is_the_one_the_simulator_draws_its_counts_at(bits):
    p = TemWaveParams(n=3.0, R=12e-9, pixel_size=0.5e-9, shape=(128, 128), apex_px=(90.3, 63.6), bits=bits, snr=12.0)
    _, truth = simulate(p)
    assert vacuum_dose(p) == pytest.approx(truth["dose"], rel=1e-12)


def _grid_twin(n, px, side):
    """The wave parameters whose twin is the stored CRB grid's case (blur 0.5 px, no coating, rotation 0,
    the core's absorption length 40 nm at 200 kV, gradient 0.04: ``bench_profiles_crb.case_fisher``)."""
    shape = (side, side)
    return TemWaveParams(
        n=n,
        R=TIP_SHAPES[int(n)],
        S=1.0,
        pixel_size=px,
        shape=shape,
        apex_px=default_apex(shape, "down", 0),
        rotation_deg=0.0,
        kv=200.0,
        core_absorption_length_200kv=40e-9,
        psf_sigma=0.5,
        illumination_gradient=0.04,
    )


@pytest.mark.parametrize("n", [2.0, 6.0])
def test_the_twin_at_the_grid_s_dose_is_the_crb_grid_s_case(n):
    """The twin's bound at the dose of edge SNR 10 is that of the CRB grid's case spelled out
    (``bench_profiles_crb.case_fisher``'s arguments): the wave parameters map onto the right
    image, and the dose onto its SNR.  The stored grid (tests/data) drew each row's apex with
    another seed: its sub-pixel position moves the bound by 2-4 %."""
    p = _grid_twin(n, 0.5e-9, 384)
    ref = fisher_information(n, TIP_SHAPES[int(n)] ** (n - 1), 0.5e-9, (384, 384), blur_sigma_px=0.5, edge_snr=10.0)
    want = crb_summary(ref)
    b = twin_bound(p, dose=ref.n_bg)
    assert b["twin_edge_snr"] == pytest.approx(10.0, rel=1e-12)
    assert b["crb_n"] == pytest.approx(want["crb_n"], rel=1e-9)
    assert b["crb_pulloff"] == pytest.approx(np.max(want["crb_dugdale"]), rel=1e-9)
    t = pd.read_csv(CRB_GRID)
    row = t[
        (t.n == n) & np.isclose(t.pixel_size_nm, 0.5) & (t.blur_px == 0.5) & (t.coating_nm == 0) & (t.edge_snr == 10)
    ]
    assert b["crb_n"] == pytest.approx(row.crb_n.iloc[0], rel=0.05)


def test_the_bound_falls_as_one_over_the_root_of_the_dose():
    p = _grid_twin(2.0, 0.5e-9, 384)
    b1, b4 = twin_bound(p, dose=1000.0), twin_bound(p, dose=4000.0)
    assert b4["crb_n"] == pytest.approx(b1["crb_n"] / 2, rel=1e-9)
    assert b4["p_dn"] > b1["p_dn"]
    assert b1["allowed_dn"] == (b1["p_dn"] >= 0.95)


KEPT_BOUNDS = Path(__file__).resolve().parents[1] / "benchmarks" / "data"
# file kept for bench_tem_bound.py --bounds-csv: (--seed0, --fix keywords, an image recomputed: a quick one)
KEPT_SETS = {
    "tem_bounds_grid.csv": (0, {}, 79),
    "tem_bounds_held_out.csv": (1000, {}, 30),
    "tem_bounds_dlc.csv": (3000, {"layer": "DLC"}, 10),
}


@pytest.mark.parametrize("name", sorted(KEPT_SETS))
def test_the_bounds_kept_for_the_benchmarks_are_this_code_s(name):
    """The three sets' bounds kept in ``benchmarks/data`` (so that ``bench_tem_bound.py`` splits a run in
    seconds, not ~30 min of Fisher computation) are what the simulator and the bound give now: one image
    of each recomputed.  Where this fails, the simulator (``tem_wave.draw_params``, ``simulate``'s dose)
    or the bound changed: compute the file again (``bench_tem_bound.py GRADES.csv --bounds-csv NEW``)."""
    from pipeline.synth.tem_wave import draw_params

    seed0, fixed, i = KEPT_SETS[name]
    kept = pd.read_csv(KEPT_BOUNDS / name)
    assert set(kept.seed0) == {seed0} and set(kept.i) == set(range(len(kept)))
    assert set(kept.fix) == {" ".join(f"{k}={v}" for k, v in sorted(fixed.items())) or "none"}
    row = kept[kept.i == i].iloc[0]
    kw = dict(layer=("none", "oxide", "DLC")[i % 3], apex_particles=bool((i // 3) % 2))  # bench_tem_independent.case
    kw.update(fixed)
    b = twin_bound(draw_params(seed0 + i, **kw))
    assert b["crb_n"] == pytest.approx(row.crb_n, rel=1e-6)
    assert b["crb_pulloff"] == pytest.approx(row.crb_pulloff, rel=1e-6)
    assert (bool(b["allowed_dn"]), bool(b["allowed_pulloff"])) == (bool(row.allowed_dn), bool(row.allowed_pulloff))
