"""`python -m pipeline --help`: one line per command saying what it does, and the usage lines
in the help name only options that exist (and every required one)."""

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline import cli

ROOT = Path(__file__).resolve().parents[1]


def subparsers():
    action = next(a for a in cli.build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices


def test_help_lists_every_command_with_its_one_line_description():
    out = subprocess.run(
        [sys.executable, "-m", "pipeline", "--help"],
        capture_output=True,
        text=True,
        env={**os.environ, "COLUMNS": "200"},
    )
    assert out.returncode == 0
    for name in subparsers():
        assert re.search(rf"^\s+{re.escape(name)}\s+{re.escape(cli.COMMAND_HELP[name])}$", out.stdout, re.MULTILINE), (
            name
        )
    assert set(cli.COMMAND_HELP) == set(subparsers())


def usage_lines():
    return [
        ln.split("python -m pipeline ", 1)[1].split()
        for ln in cli.__doc__.splitlines()
        if ln.startswith("    python -m pipeline ")
    ]


def test_usage_in_the_help_matches_the_options():
    documented = {words[0]: words[1:] for words in usage_lines()}
    assert set(documented) == set(subparsers())
    for name, sub in subparsers().items():
        known = {opt for a in sub._actions for opt in a.option_strings}
        required = {a.option_strings[0] for a in sub._actions if a.required and a.option_strings}
        named = {w.strip("[]") for w in documented[name] if w.strip("[]").startswith("--")}
        assert named <= known, f"{name}: the help names {named - known}, which do not exist"
        assert required <= named, f"{name}: required {required - named} missing from the help"


def test_inversion_reads_its_settings_from_the_workflow_config(tmp_path, monkeypatch):
    """The h grid, the laws, the solver mode and the Monte Carlo come from the workflow config
    (one place for Snakemake and a run by hand), not from options of their own."""
    import numpy as np
    import yaml

    from pipeline.config import h_grid, load_workflow_config

    options = {o for a in subparsers()["inversion"]._actions for o in a.option_strings}
    assert "--workflow-config" in options
    assert not options & {
        "--h-min",
        "--h-max",
        "--h-points",
        "--h-spacing",
        "--laws",
        "--solver-mode",
        "--mc-samples",
        "--seed",
    }
    cfg = tmp_path / "config.yaml"
    cfg.write_text(
        yaml.safe_dump(
            {
                "tips_dir": "config/tips",
                "results_dir": str(tmp_path / "results"),
                "h_grid": {"min": "0.3 nm", "max": "8 nm", "points": 7, "spacing": "linear"},
                "traction_laws": ["tri1", "dugdale"],
                "solver_mode": "rigid",
                "monte_carlo": {"samples": 123, "seed": 9},
            }
        )
    )
    called = {}
    monkeypatch.setattr("pipeline.inversion.stage.run_inversion", lambda *args, **kw: called.update(kw))
    monkeypatch.chdir(ROOT)
    assert (
        cli.main(
            [
                "inversion",
                "--tip-config",
                "config/tips/tipA_DLC.yaml",
                "--workflow-config",
                str(cfg),
                "--fits",
                "f",
                "--forces",
                "p",
                "--out-h5",
                str(tmp_path / "inv.h5"),
            ]
        )
        == 0
    )
    np.testing.assert_array_equal(called["h_grid"], np.linspace(0.3e-9, 8e-9, 7))
    np.testing.assert_array_equal(called["h_grid"], h_grid(load_workflow_config(str(cfg))))
    assert (called["laws"], called["solver_mode"], called["mc_samples"], called["seed"]) == (
        ["tri1", "dugdale"],
        "rigid",
        123,
        9,
    )


@pytest.mark.parametrize("name", ["forces", "inversion", "unlock-stale"])
def test_each_command_describes_itself_and_its_options(name):
    text = subparsers()[name].format_help()
    assert cli.COMMAND_HELP[name] in " ".join(text.split())
    # every option says what it is, except -h
    sub = subparsers()[name]
    assert all(a.help for a in sub._actions if a.option_strings and a.option_strings[0] != "-h")
