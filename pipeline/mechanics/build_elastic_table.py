"""Build the elastic pull-off table committed as pipeline/mechanics/data/elastic_pulloff_table.npz.

    OMP_NUM_THREADS=1 python -m pipeline.mechanics.build_elastic_table [--out PATH] [--processes 2]

About 6 min on one core (1536 direct solves; see pipeline.mechanics.elastic_tables).  Rebuild
and commit it whenever the grid (ELASTIC_TABLE_SPEC) or the solver (SOLVER_VERSION) changes.
"""

from __future__ import annotations

import argparse
import logging
import os

from .elastic_tables import DATA_FILE, build_elastic_table


def main(argv=None):
    p = argparse.ArgumentParser(description="Build the elastic pull-off table (L-J, Tri1, Tri2 over n, Lambda).")
    p.add_argument("--out", default=str(DATA_FILE))
    p.add_argument("--processes", type=int, default=1)
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    out = build_elastic_table(a.out, a.processes)
    os.chmod(a.out, 0o644)
    print(f"wrote {a.out} in {float(out['build_seconds']):.0f} s")


if __name__ == "__main__":
    main()
