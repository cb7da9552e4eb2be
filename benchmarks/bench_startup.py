"""Start-up cost of each stage job: from process start to the first line of stage work.

A Snakemake job runs ``python -m pipeline <command> ...``; before the command does any work the
interpreter starts and imports the stage's entry module with everything it pulls in.  For every
command this prints the wall time of a fresh ``python -c 'import pipeline.cli, <entry>'`` (and, for
the stage commands, loading the validated tip YAML, whose quantities pint parses)
(median of ``repeats`` runs, so that the disk cache is warm as in a real run), the heaviest
packages by cumulative ``-X importtime``, and whether matplotlib / scipy.stats / pandas were
imported at all.

Usage: python benchmarks/bench_startup.py [repeats, default 5] [--tree DIR: compare with another checkout]
"""

from __future__ import annotations

import importlib.util
import statistics
import subprocess
import sys
import time

# command -> candidate entry modules (the first that exists is the one the CLI imports)
ENTRIES = {
    "profiles": ["pipeline.tem.stage"],
    "fit": ["pipeline.fits.stage", "pipeline.fits"],
    "fit-figure": ["pipeline.fits.figures", "pipeline.fits"],
    "forces": ["pipeline.forces.stage"],
    "inversion": ["pipeline.inversion.stage", "pipeline.inversion"],
    "adhesion-range": ["pipeline.adhesion_range.stage", "pipeline.adhesion_range"],
    "adhesion-figures": ["pipeline.adhesion_range.figures", "pipeline.figures_adhesion"],
    "summary": ["pipeline.adhesion_range.report", "pipeline.reports"],
}
WATCH = ("matplotlib", "scipy.stats", "pandas", "scipy.optimize", "h5py", "afmformats", "skimage", "cv2", "rsciio")


def entry_module(candidates):
    for name in candidates:
        try:
            if importlib.util.find_spec(name) is not None:
                return name
        except ModuleNotFoundError:
            continue
    return None


# commands whose job reads and validates the tip YAML (units parsed by pint) before its first stage line
LOADS_TIP_CONFIG = ("profiles", "fit", "forces", "inversion", "adhesion-range")
TIP_CONFIG = "config/tips/tipA_DLC.yaml"


def job_code(module: str, loads_config: bool, tree=None) -> str:
    """What a job runs before its first line of stage work: the CLI, the entry module and, for the
    stage commands, the validated tip config (with ``tree``: that checkout's code)."""
    code = f"import sys; sys.path.insert(0, {str(tree)!r}); " if tree else ""
    code += f"import pipeline.cli, {module}"
    if loads_config:
        code += f"; import pipeline.config; pipeline.config.load_tip_config({TIP_CONFIG!r}, check_files=False)"
    return code


def wall_time(code: str) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], check=True)
    return time.perf_counter() - t0


def import_profile(code: str):
    """(packages other than pipeline by cumulative import time in s, set of watched modules imported).

    ``-X importtime`` prints a module after the modules it imported, indented by its depth; a
    line whose importer (the next line up the tree) belongs to another package starts that
    package's import, and its cumulative time is charged to the package."""
    err = subprocess.run(
        [sys.executable, "-X", "importtime", "-c", code],
        check=True,
        capture_output=True,
        text=True,
    ).stderr
    rows = []
    for line in err.splitlines():
        if not line.startswith("import time:") or line.count("|") != 2:
            continue
        _, c, raw = line[len("import time:") :].split("|")
        if not c.strip().isdigit():
            continue
        name = raw[1:]
        rows.append(((len(name) - len(name.lstrip())) // 2, name.strip(), int(c) * 1e-6))
    cum, seen = {}, {n for _, n, _ in rows if n in WATCH}
    for i, (depth, name, c) in enumerate(rows):
        parent = next((r for r in rows[i + 1 :] if r[0] < depth), None)
        top = name.split(".")[0]
        if top != "pipeline" and (parent is None or parent[1].split(".")[0] != top):
            cum[top] = cum.get(top, 0.0) + c
    return sorted(cum.items(), key=lambda kv: -kv[1]), seen


def main(repeats=5, tree=None):
    """One row per command; with ``tree`` (another checkout, e.g. a worktree of main) its start-up
    too, measured alternately in the same run, and the ratio."""
    other = f" {'other tree':>10s} {'ratio':>6s}" if tree else ""
    print(f"{'command':18s} {'entry module':34s} {'start-up (s)':>12s}{other}  heaviest imports (cumulative s); also")
    for cmd, cands in ENTRIES.items():
        mod = entry_module(cands)
        if mod is None:
            print(f"{cmd:18s} (no entry module among {cands})")
            continue
        code = job_code(mod, cmd in LOADS_TIP_CONFIG)
        times, times_other = [], []
        for _ in range(repeats):
            times.append(wall_time(code))
            if tree:
                times_other.append(wall_time(job_code(mod, cmd in LOADS_TIP_CONFIG, tree)))
        wall = statistics.median(times)
        cmp = ""
        if tree:
            w_other = statistics.median(times_other)
            cmp = f" {w_other:10.2f} {wall / w_other:6.2f}"
        top, seen = import_profile(code)
        heavy = ", ".join(f"{k} {v:.2f}" for k, v in top[:4])
        print(f"{cmd:18s} {mod:34s} {wall:12.2f}{cmp}  {heavy}; {', '.join(sorted(seen)) or '-'}")
    base = statistics.median(wall_time("import pipeline.cli") for _ in range(repeats))
    print(f"{'(interpreter + pipeline.cli only)':53s} {base:12.2f}")


if __name__ == "__main__":
    args = sys.argv[1:]
    other_tree = None
    if "--tree" in args:
        i = args.index("--tree")
        other_tree = args[i + 1]
        del args[i : i + 2]
    main(int(args[0]) if args else 5, other_tree)
