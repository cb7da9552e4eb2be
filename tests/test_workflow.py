"""End to end: Snakemake on a small generated wear test (two tips, three intervals each).

Checks the frame's promises: the run writes summary.csv with W_A and h per tip,
a second dry run has nothing to do, touching one tip's YAML reruns that tip only,
a bad tip YAML fails before any job runs, naming the file and the key, and a tip whose
jobs fail costs the other tip nothing (``--keep-going``), with the reason on the console.
"""

import csv
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from pipeline.synth.wear_test import sample_tips, write_sample_bundle

ROOT = Path(__file__).resolve().parents[1]


def small_tips():
    a, b = sample_tips()
    for t, n in ((a, [2.0, 3.8, 5.4]), (b, [2.0, 4.0, 5.8])):
        t.n, t.scans, t.curves_per_interval = n, [0, 30, 100], 5
    return [a, b]


def snakemake(workdir: Path, *args, root=ROOT):
    cmd = [
        sys.executable,
        "-m",
        "snakemake",
        "-s",
        str(root / "Snakefile"),
        "--directory",
        str(workdir),
        "--configfile",
        str(workdir / "config.yaml"),
        "--cores",
        "2",
        *args,
    ]
    return subprocess.run(
        cmd, capture_output=True, text=True, cwd=workdir, env={**os.environ, "PYTHONWARNINGS": "ignore"}
    )


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    work = tmp_path_factory.mktemp("wf")
    write_sample_bundle(work / "data", config_dir=work / "tips", tips=small_tips())
    cfg = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    cfg.update(tips_dir=str(work / "tips"), results_dir=str(work / "results"), monte_carlo={"samples": 300, "seed": 1})
    cfg["h_grid"]["points"] = 120
    (work / "config.yaml").write_text(yaml.safe_dump(cfg))
    proc = snakemake(work)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return work


def test_run_writes_summary_with_wa_and_h(finished_run):
    with open(finished_run / "results" / "summary.csv") as fh:
        rows = list(csv.DictReader(fh))
    tips = {r["tip"] for r in rows}
    assert tips == {"tipA_DLC", "tipB_Si"}
    truth = {t.name: t for t in small_tips()}
    for r in rows:
        if r["law"] != "dugdale":
            continue
        t = truth[r["tip"]]
        # small test set (3 intervals, 5 curves): loose bounds; the accuracy tests are elsewhere
        assert float(r["W_A_mJ_per_m2"]) == pytest.approx(t.W_A * 1e3, rel=0.08)
        assert float(r["h_nm"]) == pytest.approx(t.h * 1e9, rel=0.2)
    for t in truth:
        assert (finished_run / "results" / t / "profiles" / "scan000.png").stat().st_size > 10_000
        assert (finished_run / "results" / t / "W_A_vs_h.png").is_file()


def test_every_output_is_readable_as_the_umask_allows(finished_run):
    umask = os.umask(0)
    os.umask(umask)
    files = [p for p in (finished_run / "results").rglob("*") if p.is_file()]
    assert len(files) > 40
    wrong = {str(p): oct(p.stat().st_mode & 0o777) for p in files if p.stat().st_mode & 0o777 != 0o666 & ~umask}
    assert not wrong, f"expected {oct(0o666 & ~umask)}"


def test_every_report_item_has_a_caption_and_the_workflow_a_description():
    import re

    calls = [
        (smk.name, m.group(0))
        for smk in (ROOT / "workflow_rules").glob("*.smk")
        for m in re.finditer(r"report\((?:[^()]|\([^()]*\))*\)", smk.read_text())
    ]
    assert len(calls) == 8
    for smk, call in calls:
        caption = re.search(r'caption="([^"]+)"', call)
        assert caption, f"{smk}: {call} has no caption"
        text = (ROOT / "workflow_rules" / caption.group(1)).read_text()
        assert len(text.split()) > 40, caption.group(1)
    described = re.search(r'^report: "([^"]+)"', (ROOT / "Snakefile").read_text(), re.MULTILINE)
    assert described and "Where to start" in (ROOT / described.group(1)).read_text()


def test_report_shows_the_captions(finished_run, tmp_path):
    proc = snakemake(finished_run, "--report", str(tmp_path / "report.html"))
    assert proc.returncode == 0, proc.stderr[-2000:]
    html = (tmp_path / "report.html").read_text()
    assert "Where to start" in html  # the workflow description
    assert (
        html.count("What to look for") == 2 * (3 + 3 + 1 + 1 + 1 + 1) + 1
    )  # per tip: profiles, forces x3; fits, W_A(h), map, table; summary
    assert "Tip <strong>tipB_Si</strong>, interval <strong>scan030</strong>" in html  # wildcards filled in


def test_second_dry_run_has_nothing_to_do(finished_run):
    proc = snakemake(finished_run, "-n")
    assert proc.returncode == 0, proc.stderr
    assert "Nothing to be done" in proc.stdout + proc.stderr


def planned_commands(workdir, root=ROOT):
    proc = snakemake(workdir, "-n", "--printshellcmds", root=root)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    # dry-run lines read "Shell command: python -m pipeline <stage> ..."
    return [line[line.index("python -m pipeline") :] for line in out.splitlines() if "python -m pipeline" in line]


def test_touching_a_tip_yaml_without_change_reruns_nothing(finished_run):
    # Snakemake >= 9.18 compares checksums of small inputs: same content, nothing to do
    (finished_run / "tips" / "tipA_DLC.yaml").touch()
    assert planned_commands(finished_run) == []


def test_editing_one_tip_reruns_only_its_affected_stages(finished_run):
    path = finished_run / "tips" / "tipA_DLC.yaml"
    original = path.read_text()
    try:
        cfg = yaml.safe_load(original)
        cfg["cantilever"]["reference_lever"]["spring_constant_uncertainty"] = "0.03 N/m"
        path.write_text(yaml.safe_dump(cfg))
        planned = planned_commands(finished_run)
        stages = {line.split()[3] for line in planned}
        # the calibration changed: forces and everything after it, for tip A only
        assert stages == {"forces", "inversion", "adhesion-range", "adhesion-figures", "summary"}, planned
        assert not [line for line in planned if "tipB_Si" in line and " summary " not in line]
        assert sum(" forces " in line for line in planned) == 3  # tip A's three intervals
    finally:
        path.write_text(original)
    assert planned_commands(finished_run) == []


def test_the_defocus_sign_reruns_the_profiles_it_concerns(finished_run):
    """``tem.defocus`` (a stage-1 setting) reruns every profile of its tip and what follows; an
    interval's own ``defocus`` only that interval's profile (and its fit, and the tip's inversion on)."""
    path = finished_run / "tips" / "tipA_DLC.yaml"
    original = path.read_text()
    try:
        cfg = yaml.safe_load(original)
        cfg["intervals"][1]["defocus"] = "underfocus"
        path.write_text(yaml.safe_dump(cfg))
        planned = planned_commands(finished_run)
        profiles = [line for line in planned if " profiles " in line]
        assert len(profiles) == 1 and f"--interval {cfg['intervals'][1]['name']} " in profiles[0], planned
        assert not [line for line in planned if "tipB_Si" in line and " summary " not in line]
        cfg["tem"]["defocus"] = "overfocus"
        path.write_text(yaml.safe_dump(cfg))
        planned = planned_commands(finished_run)
        assert sum(" profiles " in line for line in planned) == 3  # tip A's three intervals
        assert not [line for line in planned if "tipB_Si" in line and " summary " not in line]
    finally:
        path.write_text(original)
    assert planned_commands(finished_run) == []


def test_a_code_change_reruns_its_stage_and_what_follows_only(finished_run, tmp_path):
    """An upgraded pipeline whose fit code changed reruns the fits and what follows them, not the
    profiles or the forces (the rules' `code` param, pipeline.code_version); a comment reruns nothing.
    The upgrade is a copy of the workflow and the package (Snakemake imports the package beside its
    Snakefile), planned as a dry run on the finished results."""
    upgrade = tmp_path / "upgrade"
    upgrade.mkdir()
    for part in ("Snakefile", "config", "workflow_rules", "pipeline"):
        src = ROOT / part
        if src.is_dir():
            shutil.copytree(src, upgrade / part, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(src, upgrade / part)
    module = upgrade / "pipeline" / "fits" / "power_law.py"  # imported by fits.stage via profile_fit
    module.write_text(module.read_text() + "\n# a comment only\n")
    assert planned_commands(finished_run, upgrade) == []
    module.write_text(module.read_text() + "\n_UPGRADED = True\n")
    planned = planned_commands(finished_run, upgrade)
    stages = {line.split()[3] for line in planned}
    assert stages == {"fit", "fit-figure", "inversion", "adhesion-range", "adhesion-figures", "summary"}, planned
    assert sum(" fit " in line for line in planned) == 6  # every interval of both tips
    assert planned_commands(finished_run) == []  # the installed code: nothing to do


def test_editing_the_inversion_settings_reruns_every_inversion_and_what_follows(finished_run):
    """The h grid, laws, solver mode and Monte Carlo are read by the inversion from the workflow
    config itself (--workflow-config); a change reruns the inversions of every tip, nothing before."""
    path = finished_run / "config.yaml"
    original = path.read_text()
    try:
        cfg = yaml.safe_load(original)
        cfg["monte_carlo"]["seed"] = 2
        path.write_text(yaml.safe_dump(cfg))
        planned = planned_commands(finished_run)
        assert {line.split()[3] for line in planned} == {
            "inversion",
            "adhesion-range",
            "adhesion-figures",
            "summary",
        }, planned
        inversions = [line for line in planned if " inversion " in line]
        assert len(inversions) == 2 and all("--workflow-config config.yaml " in line for line in inversions)
    finally:
        path.write_text(original)
    assert planned_commands(finished_run) == []


def test_inversion_settings_given_on_the_command_line_are_refused(finished_run):
    """--config would change what Snakemake tracks but not the file the inversion reads: one clear line."""
    proc = snakemake(finished_run, "-n", "--config", "solver_mode=rigid")
    assert proc.returncode != 0
    out = proc.stdout + proc.stderr
    assert "h_grid, traction_laws, solver_mode, monte_carlo must be set in one config file" in out, out[-2000:]


@pytest.mark.parametrize(
    "edit, needle",
    [
        (
            lambda c: c["cantilever"].update(spring_constant_method="given", spring_constant=0.9),
            "cantilever.spring_constant: 0.9 has no unit",
        ),
        (lambda c: c.update(colour="blue"), "'colour' was unexpected"),
        (lambda c: c["intervals"][1].update(image="tem/missing.tif"), "intervals[1].image"),
    ],
)
def test_bad_tip_yaml_fails_before_any_job(finished_run, tmp_path, edit, needle):
    work = tmp_path
    tips = work / "tips"
    tips.mkdir()
    cfg = yaml.safe_load((finished_run / "tips" / "tipB_Si.yaml").read_text())
    edit(cfg)
    (tips / "tipB_Si.yaml").write_text(yaml.safe_dump(cfg))
    wf = yaml.safe_load((finished_run / "config.yaml").read_text())
    wf.update(tips_dir=str(tips), results_dir=str(work / "results"))
    (work / "config.yaml").write_text(yaml.safe_dump(wf))
    proc = snakemake(work)
    assert proc.returncode != 0
    assert str(tips / "tipB_Si.yaml") in proc.stderr and needle in proc.stderr, proc.stderr[-2000:]
    assert not (work / "results").exists()  # nothing ran, nothing written


def copy_of_run(src: Path, dst: Path) -> Path:
    """A finished run in another folder (Snakemake's records keep it up to date there)."""
    shutil.copytree(src, dst, symlinks=True)
    for path in [dst / "config.yaml", *(dst / "tips").glob("*.yaml")]:
        path.write_text(path.read_text().replace(str(src), str(dst)))
    return dst


def read_summary(work):
    with open(work / "results" / "summary.csv") as fh:
        return list(csv.DictReader(fh))


def test_a_failing_tip_costs_the_other_its_summary_and_says_why_on_the_console(finished_run, tmp_path):
    work = copy_of_run(finished_run, tmp_path / "wf")
    before = read_summary(work)
    path = work / "tips" / "tipB_Si.yaml"
    cfg = yaml.safe_load(path.read_text())
    cfg.setdefault("force_curves", {})["min_pulloff_snr"] = 1e6  # every curve of tip B is rejected
    path.write_text(yaml.safe_dump(cfg))
    shutil.rmtree(work / "results" / "tipB_Si" / "forces")  # the copy has no records of params: rerun by absence

    # without --keep-going the summary is not touched and the console says how to get it
    proc = snakemake(work)
    assert proc.returncode != 0
    assert "run with --keep-going" in proc.stderr and read_summary(work) == before

    proc = snakemake(work, "--keep-going")
    assert proc.returncode != 0  # the run still fails: tip B has no result
    # the reason from the job's log stands on the console, after Snakemake's "Error in rule"
    for iv in ("scan000", "scan030", "scan100"):
        line = f"FAILED rule forces (tip=tipB_Si, interval={iv}): error (forces): "
        assert line in proc.stderr, proc.stderr[-3000:]
    assert "rejected" in proc.stderr.split("FAILED rule forces", 1)[1]
    assert f"(log: {work}/results/logs/tipB_Si/forces/scan000.log)" in proc.stderr

    rows = read_summary(work)
    assert [r for r in rows if r["tip"] == "tipA_DLC"] == [r for r in before if r["tip"] == "tipA_DLC"]
    (b,) = [r for r in rows if r["tip"] == "tipB_Si"]
    assert b["status"] == "failed" and b["W_A_mJ_per_m2"] == "" and b["h_nm"] == ""
    assert "rule forces (tip=tipB_Si, interval=scan000) failed: error (forces): " in b["notes"]
    # a summary without tip B is never taken as final: the next run writes it anew
    assert any(" summary " in line for line in planned_commands(work))
