"""The lock files that `make run` / `make test` install from: every requirement of pyproject.toml
pinned to one version that satisfies it, every pin with its sha256 hashes, the build backend
included, and the cluster lock the same versions plus the SLURM plugin."""

import importlib.util
import re
import tomllib
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("lock_drift", ROOT / "scripts" / "lock_drift.py")
lock_drift = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(lock_drift)

PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
MAIN = lock_drift.read_lock(ROOT / "requirements.lock")
CLUSTER = lock_drift.read_lock(ROOT / "requirements-cluster.lock")
LINUX_311 = {
    "python_version": "3.11",
    "python_full_version": "3.11.7",
    "sys_platform": "linux",
    "platform_system": "Linux",
    "platform_machine": "x86_64",
    "implementation_name": "cpython",
    "platform_python_implementation": "CPython",
    "os_name": "posix",
    "extra": "",
}


def requirements(*extras):
    reqs = list(PYPROJECT["project"]["dependencies"]) + list(PYPROJECT["build-system"]["requires"])
    for extra in extras:
        reqs += PYPROJECT["project"]["optional-dependencies"][extra]
    return [Requirement(r) for r in reqs]


def pins_for_linux_311(lock):
    from packaging.markers import Marker

    out = {}
    for name, entries in lock.items():
        hits = [e for e in entries if e["marker"] is None or Marker(e["marker"]).evaluate(LINUX_311)]
        assert len(hits) <= 1, f"{name} pinned twice for Linux/CPython 3.11"
        if hits:
            out[name] = hits[0]["version"]
    return out


@pytest.mark.parametrize("lock, extras", [(MAIN, ("test",)), (CLUSTER, ("test", "cluster"))], ids=["main", "cluster"])
def test_every_requirement_is_pinned_to_a_version_that_satisfies_it(lock, extras):
    pinned = pins_for_linux_311(lock)
    for req in requirements(*extras):
        name = canonicalize_name(req.name)
        assert name in pinned, f"{req} is not in the lock: run `make lock`"
        assert req.specifier.contains(pinned[name], prereleases=True), f"{name}=={pinned[name]} does not satisfy {req}"
        for extra in req.extras:  # e.g. snakemake[reports]: its extra's requirements are pinned too
            from importlib import metadata

            for dep in map(Requirement, metadata.requires(req.name) or []):
                if (
                    dep.marker is not None
                    and dep.marker.evaluate({**LINUX_311, "extra": extra})
                    and not dep.marker.evaluate(LINUX_311)
                ):
                    assert canonicalize_name(dep.name) in pinned, (
                        f"{req.name}[{extra}] needs {dep.name}, not in the lock"
                    )


@pytest.mark.parametrize("lock", [MAIN, CLUSTER], ids=["main", "cluster"])
def test_every_pin_carries_hashes(lock):
    assert len(lock) > 50
    for name, entries in lock.items():
        for e in entries:
            assert e["hashes"], f"{name}=={e['version']} has no --hash (pip --require-hashes refuses it)"


def test_cluster_lock_has_the_main_versions_plus_the_slurm_plugin():
    main, cluster = pins_for_linux_311(MAIN), pins_for_linux_311(CLUSTER)
    assert {n: cluster[n] for n in main} == main
    assert "snakemake-executor-plugin-slurm" in set(cluster) - set(main)
    assert "snakemake-executor-plugin-slurm" not in main


def test_make_installs_from_the_lock_and_ci_runs_make_test():
    makefile = (ROOT / "Makefile").read_text()
    assert "pip install --quiet --require-hashes -r $(LOCK)" in makefile
    assert "--no-deps --no-build-isolation -e ." in makefile
    ci = [
        ln for ln in (ROOT / ".ci" / "run").read_text().splitlines() if ln and not ln.startswith(("#", "set ", "cd "))
    ]
    assert ci == ["make test"]


def test_make_test_runs_the_style_checks_before_the_tests():
    """CI's `make test` runs ruff format --check, ruff check, snakefmt --check and snakemake --lint
    (make lint) before pytest, with the tools from the lock."""
    makefile = (ROOT / "Makefile").read_text()

    def recipe(target):
        lines = makefile.split(f"\n{target}:", 1)[1].splitlines()[1:]
        return [ln.strip() for ln in lines[: next(i for i, ln in enumerate(lines) if not ln.startswith("\t"))]]

    test, lint = recipe("test"), recipe("lint")
    assert test[0] == "$(MAKE) --no-print-directory lint" and test[1] == "$(BIN)/pytest"
    assert lint == [
        "$(BIN)/ruff format --check .",
        "$(BIN)/ruff check .",
        "$(BIN)/snakefmt --check Snakefile workflow_rules",
        "$(BIN)/snakemake --lint",
    ]
    pins = pins_for_linux_311(MAIN)
    assert "ruff" in pins and "snakefmt" in pins


def test_drift_names_what_differs_from_the_lock(tmp_path):
    lock = tmp_path / "x.lock"
    lock.write_text(
        "pytest==0.0.1 \\\n    --hash=sha256:" + "a" * 64 + "\n    # via x\n"
        "nosuchpackage-xyz==1.0 ; python_version >= '3.0' \\\n    --hash=sha256:" + "b" * 64 + "\n"
    )
    pins = lock_drift.read_lock(lock)
    assert (
        pins["pytest"][0]["hashes"] == ["a" * 64]
        and pins["nosuchpackage-xyz"][0]["marker"] == "python_version >= '3.0'"
    )
    lines = lock_drift.drift(lock)
    assert any(ln.startswith("pytest 0.0.1 -> ") for ln in lines)
    assert "nosuchpackage-xyz 1.0 pinned, not installed" in lines


# Licences GPL-3.0-or-later cannot take in (README "Licence"); matched in each locked package's
# licence metadata (expression, licence text's first line, classifiers).
INCOMPATIBLE = re.compile(
    r"GPL-2\.0-only|GPLv2 only|GPL-2\.0\b(?!.*or.later)|SSPL|BUSL|Business Source|Proprietary|"
    r"Commercial|Non.?Commercial|CC-BY-NC|Elastic License",
    re.IGNORECASE,
)


def test_licence_is_gpl3_or_later_and_no_locked_dependency_forbids_it():
    from importlib import metadata

    assert PYPROJECT["project"]["license"] == "GPL-3.0-or-later"
    text = (ROOT / "LICENSE").read_text()
    assert text.split()[:6] == ["GNU", "GENERAL", "PUBLIC", "LICENSE", "Version", "3,"] and len(text) > 30000
    checked = 0
    for name in pins_for_linux_311(MAIN):
        try:
            meta = metadata.metadata(name)
        except metadata.PackageNotFoundError:
            continue
        words = [meta.get("License-Expression") or "", (meta.get("License") or "").split("\n")[0]]
        words += [c for c in meta.get_all("Classifier") or [] if c.startswith("License")]
        assert not INCOMPATIBLE.search(" | ".join(words)), f"{name}: {words}"
        checked += 1
    assert checked > 80
