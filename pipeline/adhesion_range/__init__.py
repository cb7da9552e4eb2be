"""Stage 5: the adhesion range h where the worn intervals' W_A(h) meet the reference.

Paper Sec. 4.1 (Fig. 3b/d) and Sec. 4.3 (Table 1): W_A is assumed constant over the
wear test and is taken from the paraboloidal (n ~ 2) reference interval(s), whose
W_A(h) is nearly independent of h.  For a worn interval (n > 2), W_A(h) depends
strongly on h; h is where the two curves meet.

Per traction law (``analysis.analyse_law``):

* ``reference``: the reference curve W_ref(h), inverse-variance weighted mean of ln W_A(h) of
  the reference intervals, per MC sample; its value and its variation over the grid;
* ``crossings``: per worn interval the roots of D(h) = ln W(h) - ln W_ref(h), with an explicit
  status, never a made-up number;
* ``global_fit``: a global estimate, the generalised-least-squares common W_A at every h with
  the covariance of the Monte Carlo, h = argmin chi2; its CI from repeating it per MC sample;
* ``inconsistency``: where the intervals disagree more than their uncertainties allow, a
  between-interval random effect (default) or the Birge scaling widens the CIs, and the note
  says so;
* ``curves``: ln W_A curves and their sample percentiles.

``io`` writes and reads ``adhesion_range.h5`` (the only place its layout is spelled), ``report``
the per-tip CSV and ``summary.csv``, ``figures`` the W_A(h) figure (Fig. 3b/d) and the adhesion
map (Fig. 5); ``stage.run_adhesion_range`` is the command-line stage.

Range conventions: L-J in the z0 = h/0.974 convention (the h reported is the
Dugdale-equivalent h; z0 is given too); Tri2 h is the Dugdale-equivalent h (separation
of the peak stress); its full range 2h is reported separately (the paper's Table 1
uses 2h for Tri2).
"""
