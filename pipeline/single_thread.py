"""One BLAS / OpenMP thread for a computation whose result must not depend on the machine's core count.

OpenBLAS splits a matrix product among its threads, and each thread count sums in another order: the
last bits of J^T J, of a solve, of a norm differ.  A well-conditioned fit does not notice; the TEM
stage's fits do where they stop on a threshold or choose between basins (README, "Same result on any
machine"): interval 1 of tip 1068 of ``bench_wear_test_wave`` ended its fringe correction at chi^2
103912 (lambda df 151 px^2) on one thread and at 22917 (129 px^2) on two.  Snakemake already runs a
rule's shell command with ``OPENBLAS_NUM_THREADS`` set to the rule's threads (1 here), but a stage run
by hand, from a notebook or by the tests took the machine's core count.  The functions wrapped here run
on one thread whatever the environment says, so the thread count is no longer part of the arithmetic
path; the benchmarks, which always ran on one thread, keep their numbers.
"""

from __future__ import annotations

import functools

from threadpoolctl import threadpool_limits

__all__ = ["single_threaded"]


def single_threaded(fn):
    """``fn`` with every BLAS and OpenMP thread pool limited to one thread while it runs (restored after).

    The limit is the process's (threadpoolctl sets the libraries' own thread counts) and reaches only the
    libraries loaded by then (numpy's and scipy's OpenBLAS are, once ``pipeline.tem`` is imported): two
    Python threads running such functions at once would restore each other's counts in any order."""

    @functools.wraps(fn)
    def on_one_thread(*args, **kwargs):
        with threadpool_limits(limits=1):
            return fn(*args, **kwargs)

    return on_one_thread
