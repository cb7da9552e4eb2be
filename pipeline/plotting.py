"""What the stages' figures share: matplotlib without a display (``plt`` is pyplot on the Agg
backend), log axes labelled with plain numbers, and PNG files written atomically.  Only figure
modules import this (it loads matplotlib)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter  # noqa: E402

from pipeline.h5io import atomic_output  # noqa: E402

__all__ = ["plt", "plain_log_axis", "save_png"]


def plain_log_axis(axis) -> None:
    """Log axis with plain-number labels at 1-2-5 steps and unlabelled minor ticks."""
    axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    axis.set_minor_formatter(NullFormatter())


def save_png(fig, out_png, dpi=None) -> None:
    """Write ``fig`` to ``out_png`` atomically (``dpi`` None: the figure's) and close it."""
    with atomic_output(out_png) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    plt.close(fig)
