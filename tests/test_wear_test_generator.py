"""The sample-data generator is deterministic and its truth is self-consistent."""

import hashlib

import pytest
import yaml

from pipeline.synth.wear_test import sample_tips, tip_config, write_sample_bundle


def digest(folder):
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def small_tip():
    t = sample_tips()[1]
    t.n, t.scans, t.curves_per_interval = [2.0, 5.0], [0, 50], 2
    return t


def test_same_seed_same_bytes(tmp_path):
    write_sample_bundle(tmp_path / "a", config_dir=tmp_path / "ca", tips=[small_tip()])
    write_sample_bundle(tmp_path / "b", config_dir=tmp_path / "cb", tips=[small_tip()])
    assert digest(tmp_path / "a") == digest(tmp_path / "b")


def test_truth_matches_config_and_physics(tmp_path):
    t = small_tip()
    write_sample_bundle(tmp_path / "d", config_dir=tmp_path / "c", tips=[t])
    truth = yaml.safe_load((tmp_path / "d" / t.name / "truth.yaml").read_text())
    # n = 2 with the rigid (DMT) limit: F_p close to 2 pi R W (M-D-n, Lambda ~ 0.005 here)
    F0 = truth["intervals"][0]["F_p_true_N"]
    assert F0 == pytest.approx(2 * 3.141592653589793 * t.R * t.W_A, rel=0.01)
    cfg = yaml.safe_load((tmp_path / "c" / f"{t.name}.yaml").read_text())
    assert cfg == yaml.safe_load(yaml.safe_dump(tip_config(t, data_dir=str(tmp_path / "d" / t.name))))
    assert cfg["reference_intervals"] == ["scan000"]
