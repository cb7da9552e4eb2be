"""Run time of the TEM stage (image file -> apex profile) per image, this tree against a baseline.

    .venv/bin/python benchmarks/bench_tem_speed.py --baseline-rev main [--repeats 3] [--cache DIR]
    .venv/bin/python benchmarks/bench_tem_speed.py --baseline /path/to/checkout

Images: both generators (``pipeline.synth.tem_image`` Beer-Lambert renderer, ``pipeline.synth.tem_wave``
wave-optical simulator) x 512 / 1024 px x uncoated / coated (1.5 nm and 1.4 nm oxide), at the small
pixels (0.105-0.12 nm) of the largest tips that ``bench_tem_independent`` draws (the fitted band
grows with the profile height in pixels; pixels finer than 0.2 nm are fitted unbinned), plus the
2048 px image of ``bench_profiles`` (0.1 nm, fitted on 2 x 2 blocks), and the first image of each
sample tip (``data_samples``: tip A 15 nm DLC, tip B 1.5 nm oxide, 512 px).  Each is saved as a
calibrated TIFF and read back (``read_tem_image``), then ``extract_profile`` with the workflow
defaults.

Every tree runs in its own process (PYTHONPATH set to it) on one thread; the processes alternate,
``--repeats`` times, and the least time per image counts.  Times are the process's CPU time
(``time.process_time``: one thread, so the work of one core without the waits of a shared
machine; contention still inflates it, so compare the ratio, not the absolute seconds).  ``--baseline-rev`` makes
a temporary ``git worktree`` of that revision and removes it afterwards.

Prints per image: seconds (baseline, this tree, ratio), the LM iterations (equal: the same
path), and this tree's time split by phase: read (file -> array), coarse (tip, axis, window,
initial contour), single (single-layer silhouette fit), coating (coated-model search), exact
(finite-difference Jacobian at the solution, for the covariance), refine (its Gauss-Newton
steps), rest (reference curve and pixel set, the output silhouette, symmetry frame and profile
sampling).  Never fails on time.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core (set before numpy loads, in the workers too)

REPO = Path(__file__).resolve().parents[1]
PHASES = ("read", "coarse", "single", "coating", "exact", "refine", "rest")
NM = 1e-9
SAMPLE_TIPS = ("tipA_DLC", "tipB_Si")


def cases():
    """(name, generator, size, coated, keywords) of the images."""
    out = []
    for size, px in ((512, 0.12 * NM), (1024, 0.105 * NM)):
        for coated in (False, True):
            out.append((f"BL {size} {'coated' if coated else 'bare'}", "beer-lambert", size, coated, dict(px=px)))
            out.append((f"wave {size} {'coated' if coated else 'bare'}", "wave", size, coated, dict(px=px)))
    out.append(("BL 2048 bare (0.1 nm)", "beer-lambert-2048", 2048, False, {}))
    return out


def render(gen, size, coated, kw):
    """(image array as saved, pixel size m)."""
    if gen == "beer-lambert":
        from pipeline.synth.tem_image import render_tem_image

        px = kw["px"]
        img, _ = render_tem_image(
            3.0,
            (12 * NM) ** 2,  # Q of n = 3, R = 12 nm, S = 1 (Eq. 2)
            px,
            shape=(size, size),
            blur_sigma_px=1.2,
            edge_snr=15,
            rotation_deg=4.0,
            coating_thickness=1.5 * NM if coated else 0.0,
            seed=size + (15 if coated else 0),
        )
        return img, px
    if gen == "beer-lambert-2048":  # the image bench_profiles times
        from pipeline.synth.tem_image import render_tem_image

        img, _ = render_tem_image(3.0, (15 * NM) ** 2, 0.1 * NM, shape=(2048, 2048), edge_snr=20, seed=7)
        return img, 0.1 * NM
    from pipeline.synth.tem_wave import draw_params, simulate

    p = draw_params(
        11 if size == 512 else 12,
        layer="oxide" if coated else "none",
        shape=(size, size),
        pixel_size=kw["px"],
        apex_particles=False,
        orientation="down",
    )
    img, _ = simulate(p)
    return img, p.pixel_size


def make_images(directory):
    """Render (once per cache directory) and save every case as a calibrated TIFF, then the sample
    tips' first images (512 x 512, DLC and oxide): {name: path}."""
    from pipeline.synth.tem_wave import write_image

    paths = {f"sample {tip} scan000": str(REPO / "data_samples" / tip / "tem" / "scan000.tif") for tip in SAMPLE_TIPS}
    for name, gen, size, coated, kw in cases():
        path = Path(directory) / (name.replace(" ", "_").replace("(", "").replace(")", "") + ".tif")
        if not path.exists():
            img, px = render(gen, size, coated, kw)
            write_image(path, img, px)
        paths[name] = str(path)
    return paths


class _PhaseTimer:
    """Exclusive times of the phases: wraps the functions (looked up at call time) of a tree."""

    def __init__(self):
        self.t = dict.fromkeys(PHASES, 0.0)
        self.stack = []

    def wrap(self, owner, attr, phase):
        fn = getattr(owner, attr)

        def timed(*a, **k):
            t0 = time.process_time()
            self.stack.append(0.0)
            try:
                return fn(*a, **k)
            finally:
                dt = time.process_time() - t0
                inner = self.stack.pop()
                self.t[phase] += dt - inner
                if self.stack:
                    self.stack[-1] += dt

        setattr(owner, attr, timed)

    def install(self):
        import pipeline.tem.profiles as prof
        import pipeline.tem.silhouette_fit as sf
        from pipeline.tem.silhouette_solver import _Fitter

        self.wrap(prof, "locate_tip", "coarse")
        self.wrap(prof, "_window_and_contour", "coarse")
        self.wrap(sf, "_single_layer_fit", "single")
        self.wrap(sf, "_coating_search", "coating")
        self.wrap(_Fitter, "polish", "refine")
        self.wrap(_Fitter, "exact_jacobian", "exact")


def worker(paths):
    """Time every image (one process, this PYTHONPATH's tree); prints one JSON line."""
    from pipeline.tem.profiles import extract_profile
    from pipeline.tem.reading import read_tem_image

    timer = _PhaseTimer()
    timer.install()
    extract_profile(read_tem_image(paths[0]))  # warm-up: imports, caches
    out = {}
    for path in paths:
        timer.t = dict.fromkeys(PHASES, 0.0)
        t0 = time.process_time()
        image = read_tem_image(path)
        t1 = time.process_time()
        prof = extract_profile(image)
        t2 = time.process_time()
        phases = dict(timer.t, read=t1 - t0)
        phases["rest"] = (t2 - t1) - sum(v for k, v in phases.items() if k not in ("read", "rest"))
        out[path] = dict(total=t2 - t0, iterations=prof.edge_model.get("global_iterations"), phases=phases)
    print(json.dumps(out))


def run_tree(tree, paths):
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    res = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--worker", *paths],
        env=env,
        cwd=str(tree),
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(res.stdout.strip().splitlines()[-1])


def _best(runs, path):
    """The least-time run of one image (its phases with it)."""
    return min((r[path] for r in runs), key=lambda r: r["total"])


def report(paths, base_runs, new_runs, label):
    print(f"\nCPU seconds per image (least of {len(new_runs)} runs each; one thread), baseline = {label}")
    head = f"{'image':24s} {'base s':>7s} {'this s':>7s} {'ratio':>6s} {'iter':>9s} |"
    print(head + "".join(f" {p:>7s}" for p in PHASES))
    for name, path in paths.items():
        b, n = _best(base_runs, path), _best(new_runs, path)
        it = f"{b['iterations']}/{n['iterations']}"
        row = f"{name:24s} {b['total']:7.2f} {n['total']:7.2f} {n['total'] / b['total']:6.2f} {it:>9s} |"
        print(row + "".join(f" {n['phases'][p]:7.3f}" for p in PHASES))
    print("\nbaseline time split (s):")
    print(f"{'image':24s}" + "".join(f" {p:>7s}" for p in PHASES))
    for name, path in paths.items():
        b = _best(base_runs, path)
        print(f"{name:24s}" + "".join(f" {b['phases'][p]:7.3f}" for p in PHASES))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worker", nargs="+", help=argparse.SUPPRESS)
    ap.add_argument("--baseline", help="a checkout of the code to compare with")
    ap.add_argument("--baseline-rev", help="git revision to compare with (temporary worktree)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--cache", help="directory for the rendered images (kept)")
    args = ap.parse_args(argv)
    if args.worker:
        return worker(args.worker)
    if not (args.baseline or args.baseline_rev):
        ap.error("give --baseline DIR or --baseline-rev REV")
    with tempfile.TemporaryDirectory() as tmp:
        base, label = args.baseline, args.baseline
        if args.baseline_rev:
            base = os.path.join(tmp, "baseline")
            subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", base, args.baseline_rev], check=True)
            label = args.baseline_rev
        try:
            t0 = time.perf_counter()
            paths = make_images(args.cache or tmp)
            print(f"{len(paths)} images ready ({time.perf_counter() - t0:.0f} s)", flush=True)
            base_runs, new_runs = [], []
            for _ in range(args.repeats):  # alternate, so that both see the same load
                base_runs.append(run_tree(base, list(paths.values())))
                new_runs.append(run_tree(REPO, list(paths.values())))
            report(paths, base_runs, new_runs, label)
        finally:
            if args.baseline_rev:
                subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", base], check=False)


if __name__ == "__main__":
    main()
