"""Pull-offs read right on jittered ramps, and a curve's own uncertainty counts in the interval mean.

The jitter curves come from ``make_force_curve(height_jitter=...)``: ``sensor`` (the height
record is noisy, the lever follows the smooth ramp: a line fitted against height is flattened
by the errors in its abscissa and read Delta ~20 % low before) and ``piezo`` (the piezo itself
jitters, the lever follows it and can rise and fall along its contact line before it lets go).
The statistics of the weighted mean are checked by simulation, not against their own formulas.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from pipeline.forces.pulloff import detect_pulloff
from pipeline.forces.statistics import interval_stats, random_effects_mean
from pipeline.synth.force_curves import make_force_curve

INVOLS = 50e-9


def _read(F_p, k, seed, **kw):
    c = make_force_curve(F_p, k, INVOLS, seed=seed, noise=0.1e-9, **kw)
    r = c.segment == "retract"
    po = detect_pulloff(1e-6 - c.height[r], c.deflection_V[r] * INVOLS)
    return po.delta * k / F_p - 1.0, po.u_delta * k / F_p


@pytest.mark.parametrize(
    "jitter, amplitude, fk, max_mean, max_worst",
    [
        ("sensor", 0.5e-9, 10e-9, 0.006, 0.03),  # 5 x the 0.1 nm step
        ("sensor", 1.0e-9, 3e-9, 0.015, 0.08),
        ("piezo", 0.2e-9, 10e-9, 0.008, 0.06),
    ],
)
def test_jittered_pulloff_unbiased_and_covered(jitter, amplitude, fk, max_mean, max_worst):
    k = 0.5
    err, u = np.array([_read(fk * k, k, s, height_jitter=amplitude, jitter=jitter) for s in range(60)]).T
    assert abs(err.mean()) < max_mean, err.mean()
    assert np.abs(err).max() < max_worst, np.abs(err).max()
    assert np.mean(np.abs(err) < 2.0 * u) >= 0.85  # the curve's own uncertainty covers its error


def test_clean_ramp_reading_unchanged_by_jitter_handling():
    """No jitter: the height fit is kept (the index fit is only used when clearly better)."""
    err, u = np.array([_read(5e-9, 0.5, s) for s in range(40)]).T
    assert abs(err.mean()) < 0.004 and np.abs(err).max() < 0.02
    assert np.mean(np.abs(err) < 2.0 * u) >= 0.85


def test_random_effects_mean_equal_u_is_plain_mean():
    x = np.array([1.0, 1.1, 0.95, 1.05, 0.98])
    m, sem, tau, w = random_effects_mean(x, np.full(5, 0.01))
    assert m == pytest.approx(x.mean(), rel=1e-12)
    assert sem == pytest.approx(x.std(ddof=1) / np.sqrt(5), rel=1e-12)
    assert np.allclose(w, 0.2)
    assert tau == pytest.approx(np.sqrt(x.var(ddof=1) - 0.01**2), rel=1e-9)


def test_random_effects_interval_covers_at_nominal_rate():
    """Simulated intervals (8 curves, 3 % genuine scatter, per-curve u from 0.3 to 3 %, one
    curve in four ten times worse): mean +- t(n-1) sem covers the true mean ~95 % of the time."""
    rng = np.random.default_rng(7)
    hits, n, reps = 0, 8, 3000
    for _ in range(reps):
        u = rng.uniform(0.003, 0.03, n)
        u[rng.random(n) < 0.25] *= 10
        x = 1.0 + 0.03 * rng.standard_normal(n) + u * rng.standard_normal(n)
        m, sem, _, _ = random_effects_mean(x, u)
        hits += abs(m - 1.0) <= stats.t.ppf(0.975, n - 1) * sem
    assert 0.93 <= hits / reps <= 0.985


def test_one_uncertain_curve_cannot_move_the_mean():
    """The held-out failure: one curve read 21 % low with 170 x the median uncertainty, in an
    8-curve interval with 3 % scatter: the unweighted mean moved ~2.6 %, the weighted one stays."""
    rng = np.random.default_rng(3)
    x = 1.0 + 0.03 * rng.standard_normal(8)
    u = np.full(8, 0.003)
    x[5], u[5] = 0.79, 0.5
    used = np.ones(8, bool)
    plain = interval_stats(x, used, rule="modified_z", threshold=np.inf)
    weighted = interval_stats(x, used, rule="modified_z", threshold=np.inf, u=u)
    clean = np.delete(x, 5).mean()
    assert abs(plain.mean / clean - 1) > 0.02
    assert abs(weighted.mean / clean - 1) < 0.003
    assert weighted.weight[5] < 0.01 and weighted.weight.sum() == pytest.approx(1.0)


def test_stage_weights_a_noisy_curve_down(tmp_path):
    """Forces stage end to end: one curve of eight with 10 x the deflection noise gets a small
    weight (HDF5 curves/weight) and the interval mean stays within 1 % of the others' truth."""
    import h5py

    from pipeline.forces.stage import run_forces
    from pipeline.synth.force_curves import write_curve_csv

    rng = np.random.default_rng(11)
    k, paths, F = 0.5, [], 5e-9 * (1 + 0.03 * rng.standard_normal(8))
    for j, Fj in enumerate(F):
        c = make_force_curve(float(Fj), k, INVOLS, seed=j, noise=1.2e-9 if j == 2 else 0.1e-9)
        paths.append(write_curve_csv(tmp_path / f"c{j}.csv", c))
    out = tmp_path / "f.h5"
    run_forces(
        paths,
        out,
        tmp_path / "f.png",
        cantilever={
            "spring_constant": k,
            "deflection_sensitivity": INVOLS,
            "method": "given",
            "base_dir": str(tmp_path),
        },
        reader={},
        tip="t",
        interval="i",
        interval_cfg={},
    )
    with h5py.File(out) as f:
        w = f["curves/weight"][()]
        mean = f["interval/F_p_mean"][()]
    assert w[2] < 0.5 / 8
    assert abs(mean / np.delete(F, 2).mean() - 1) < 0.01


def test_clipped_pulloff_is_rejected_with_the_reason(tmp_path):
    """Every curve of an interval clipped at the detector's limit (the adhesive dip flat at the
    rail): each is rejected as clipped and the stage refuses the interval (before: F_p 51 % low,
    8 of 8 curves used, no flag).  A 12-bit ADC's flat steps at a genuine minimum are no clipping."""
    from pipeline.forces.errors import ForceCurveError, ForcesStageError
    from pipeline.forces.stage import run_forces
    from pipeline.synth.force_curves import write_curve_csv

    k, F = 0.5, 10e-9
    paths = []
    for j in range(8):
        c = make_force_curve(F, k, INVOLS, seed=j, noise=0.1e-9)
        c.deflection_V[:] = np.maximum(c.deflection_V, -0.1)  # the dip (-0.4 V) cut at -0.1 V
        paths.append(write_curve_csv(tmp_path / f"c{j}.csv", c))
        r = c.segment == "retract"
        with pytest.raises(ForceCurveError, match="clipped"):
            detect_pulloff(1e-6 - c.height[r], c.deflection_V[r])
    with pytest.raises(ForcesStageError, match="clipped"):
        run_forces(
            paths,
            tmp_path / "f.h5",
            tmp_path / "f.png",
            cantilever={
                "spring_constant": k,
                "deflection_sensitivity": INVOLS,
                "deflection_sensitivity_method": "given",
            },
            reader={},
            tip="t",
            interval="i",
        )
    assert not (tmp_path / "f.h5").exists()
    # quantised to 12 bits over +-10 V (4.9 mV, 0.24 nm): flat runs, read as before
    c = make_force_curve(F, k, INVOLS, seed=3, noise=0.05e-9)
    lsb = 20.0 / 4096
    r = c.segment == "retract"
    po = detect_pulloff(1e-6 - c.height[r], np.round(c.deflection_V[r] / lsb) * lsb)
    assert po.delta * INVOLS * k / F == pytest.approx(1.0, abs=0.02)
