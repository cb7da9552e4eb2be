"""Stage 4: invert measured pull-off forces into W_A(h) for every wear interval.

For each interval of a tip and each traction law the work of adhesion is computed on
an h grid (paper Sec. 4.1, Fig. 3b/d): W_A(h) = work_of_adhesion(F_p, n, Q, E*, h).
The central curve uses the best estimates; a seeded Monte-Carlo propagates the pull-off force
of the interval, the calibration (k once per tip, InvOLS per interval), the power-law fit
(n, ln Q) and E* (``montecarlo``).

Modules:

* ``laws``: the traction laws, solver modes and how each law reports h;
* ``shape``: which shape an interval is inverted with (the n < 2 policy, the paraboloid of a
  reference interval, fits flagged unusable);
* ``solve``: W_A(h) per law in the solver mode (rigid / full elastic model / auto by Eq. 13 or
  the law's own boundary), Lambda and the rigid regime;
* ``montecarlo``: the seeded draws;
* ``calibration``: checks and corrections of the forces (k shared by the tip, implausible
  pull-offs, the tip's contact compliance in a contact-slope InvOLS);
* ``hgrid``: the h grid, its Monte-Carlo subset and interpolation in ln h;
* ``io``: the stage-2 fit reader ``load_fit`` (from ``pipeline.fits.io``), the inversion file's writer and its reader
  ``load_inversion``;
* ``stage``: :func:`~pipeline.inversion.stage.run_inversion`, the command-line stage.
"""

from pipeline.inversion.shape import UNUSABLE_FIT_FLAGS, clip_n  # the interval policy, used by pipeline.synth

__all__ = ["UNUSABLE_FIT_FLAGS", "clip_n"]
