"""The code version a rule carries (``pipeline.code_version``): which modules a stage runs, and which
edits of them change the hash (code) or not (comments, line layout)."""

import textwrap
from pathlib import Path

import pytest

from pipeline.code_version import code_version, stage_modules

ROOT = Path(__file__).resolve().parents[1]


def write(root: Path, rel: str, text: str):
    path = root / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(text))


@pytest.fixture
def tree(tmp_path):
    """A small ``pipeline`` package: stage imports core at module level, helpers inside a function
    (relative), core imports pipeline.shared; other is imported by nobody."""
    write(tmp_path, "pipeline/__init__.py", '"""pkg"""\n')
    write(tmp_path, "pipeline/a/__init__.py", "")
    write(
        tmp_path,
        "pipeline/a/stage.py",
        """
        import numpy as np
        from pipeline.a import core


        def run(x):
            from .helpers import twice

            return twice(core.f(x)) + np.zeros(1)
        """,
    )
    write(tmp_path, "pipeline/a/core.py", "from pipeline.shared import K\n\n\ndef f(x):\n    return K * x\n")
    write(tmp_path, "pipeline/a/helpers.py", "def twice(x):\n    return 2 * x\n")
    write(tmp_path, "pipeline/shared.py", "K = 3\n")
    write(tmp_path, "pipeline/other.py", "Z = 1\n")
    return tmp_path


def test_a_stage_runs_the_modules_it_imports_anywhere_and_its_packages(tree):
    assert stage_modules("pipeline.a.stage", root=tree) == {
        "pipeline",
        "pipeline.a",
        "pipeline.a.stage",
        "pipeline.a.core",
        "pipeline.a.helpers",
        "pipeline.shared",
    }


def test_a_code_change_anywhere_in_the_stage_changes_its_version_and_only_its(tree):
    before = code_version("pipeline.a.stage", root=tree)
    other = code_version("pipeline.other", root=tree)
    write(tree, "pipeline/shared.py", "K = 4\n")  # two imports away
    assert code_version("pipeline.a.stage", root=tree) != before
    assert code_version("pipeline.other", root=tree) == other


def test_comments_and_line_layout_leave_the_version_unchanged(tree):
    before = code_version("pipeline.a.stage", root=tree)
    write(
        tree,
        "pipeline/a/core.py",
        """
        # a comment
        from pipeline.shared import K  # another


        def f(
            x
        ):

            return K * x  # reformatted
        """,
    )
    assert code_version("pipeline.a.stage", root=tree) == before


def test_moving_a_statement_out_of_its_block_changes_the_version(tree):
    write(tree, "pipeline/a/helpers.py", "def twice(x):\n    if x:\n        x = 1\n    return 2 * x\n")
    inside = code_version("pipeline.a.stage", root=tree)
    write(tree, "pipeline/a/helpers.py", "def twice(x):\n    if x:\n        x = 1\n        return 2 * x\n")
    assert code_version("pipeline.a.stage", root=tree) != inside


def test_an_unknown_entry_module_is_an_error_naming_it(tree):
    with pytest.raises(ModuleNotFoundError, match="pipeline.a.nothing"):
        code_version("pipeline.a.nothing", root=tree)


def test_the_real_stages():
    """Every module a rule names exists; stage 1 includes the silhouette fit, and no stage runs the
    synthetic-data generators (``pipeline.synth`` is imported by no stage)."""
    smk = (ROOT / "workflow_rules" / "common.smk").read_text()
    names = {"pipeline.tem.stage", "pipeline.fits.stage", "pipeline.forces.stage", "pipeline.inversion.stage"}
    assert all(f'"{n}"' in smk for n in names)
    tem = stage_modules("pipeline.tem.stage", "pipeline.config")
    assert {"pipeline.tem.silhouette_fit", "pipeline.tem.fringe_correction", "pipeline.config"} <= tem
    for n in names | {"pipeline.adhesion_range.stage"}:
        assert not [m for m in stage_modules(n) if m.startswith("pipeline.synth")], n
    assert len(code_version("pipeline.tem.stage")) == 12
