"""Coating search of the silhouette fit: starts of the coated model under the single-layer fit,
their convergence and the decision whether a light outer layer is seen (``COAT_DCHI2``)."""

from __future__ import annotations

import numpy as np

COAT_DCHI2 = 10.0  # chi^2 decrease needed to accept a coating layer (2 extra parameters, p ~ 0.5 %)
# layer thicknesses (px) tried as starts of the coated fit; a start converges to the layer
# only within ~30 % of its thickness (measured on 96 synthetic cases, oxide 1-2.5 nm)
COAT_GRID_PX = (1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.5, 9.0, 11.0)
# a hidden light layer (contrast ratio 1/3) widens the single-layer blur: sigma_single^2 ~
# sigma^2 + BLUR_PER_COAT t^2 (px; 0.25-0.31 measured for t = 2-6 px, blur 0.5 and 2 px)
BLUR_PER_COAT = 0.28
# thicker layers than COAT_PER_BLUR x sigma_single are not tried: the relation allows
# t <= 1.9 sigma_single with no blur at all; layers of weaker contrast widen the blur less
# (ratio 0.5: t/sigma_single <= 1.7, ratio 0.7: <= 2.4 measured), 0.8 is not accepted anyway
COAT_PER_BLUR = 2.6
# the floor of the fitted blur (px; the silhouette fit's bound): phase contrast sharpens the edge of
# a defocused image, and there the blur sits at it whatever the layer (95 of the 117 used grid images
# of ``bench_tem_independent``), so the blur leaves no room for a layer (``silhouette_fit``, "A layer
# read as a fringe")
BLUR_FLOOR_PX = 0.25
# thinnest layer that counts as one (px, the smallest start of the search): with the coated model
# continuous in the thickness, a 1.1 px layer of contrast 0.45 under a 1 px blur absorbed the
# single-layer model's own error on a noise-free uncoated flat face (chi^2 -19, edge 0.1 nm out)
MIN_COAT_PX = 1.5
# layer/core attenuation ratios that count as a layer: a DLC coating has 5-30 % of the core's
# contrast (issue 16; grid image 38, DLC at 0.068, converged at 0.05-0.08 and was called ambiguous
# under the former 0.1); near 1 the two layers are one, the single layer fitting noise
PHYSICAL_RATIO = (0.04, 0.8)
COAT_START_ITERS = 3  # full LM iterations from each of the two best starts
COAT_EXTRA_STARTS = 3  # further starts tried when the decision is borderline


def _coated_start(f1, st1, lim2, thickness):
    """Coated-model parameters for a layer of ``thickness`` px under the single-layer fit ``st1``.

    The single-layer edge of a hidden light layer lies inside the outer surface by about half
    the layer (outer = single + t/2), and the fit widened its blur to absorb the layer:
    sigma_single^2 ~ sigma^2 + BLUR_PER_COAT t^2, so the layer's own blur is what is left."""
    c1, sg1, ko1, _, _ = f1.unpack(st1.v)
    sg = np.sqrt(max(sg1**2 - BLUR_PER_COAT * thickness**2, 0.3**2))
    v = np.concatenate([c1 + 0.5 * thickness, [np.log(sg), np.log(ko1 * 0.3), np.log(ko1 * 1.2), np.log(thickness)]])
    return np.clip(v, lim2[0] + 1e-6, lim2[1] - 1e-6)


def _converge(f2, st, cost1, lim2, max_iter, chunk=3):
    """LM on a coated fit to convergence, in chunks; stopped early once it is clearly worse
    than the single layer (chi^2 above it by > 3 COAT_DCHI2) and a chunk recovers less than a
    quarter of that deficit.  A start far below may still be on its way (noise-free images
    have one at -2e6 reach +1.4e5), one creeping at -40 is not.  Returns (state, iterations)."""
    n_it = 0
    while n_it < max_iter:
        before = st.cost
        st, _, _, it = f2.run(st.v, "full", min(chunk, max_iter - n_it), *lim2)
        n_it += it
        deficit = st.cost - cost1
        if it < chunk or (deficit > 3 * COAT_DCHI2 and before - st.cost < 0.25 * deficit):
            break
    return st, n_it


def _coating_search(f1, st1, f2, lim2, coat_hint, max_coat, max_iter, blur_room=True):
    """Best physical coated fit and the coating decision (module doc, "Coating").

    The coated chi^2 surface has a basin per layer thickness: LM finds the layer only from
    a start within ~30 % of its thickness (and with the shape free: a uniform shift of the
    single-layer edge does not reach it on a blunt tip, whose flat face sees the layer through
    a longer chord than the flanks).  So: every thickness of ``COAT_GRID_PX`` that the
    single-layer blur leaves room for (t <= COAT_PER_BLUR sigma_single) is evaluated once
    from ``_coated_start``, the two best get ``COAT_START_ITERS`` full LM iterations and the
    better one is converged.  Only PHYSICAL fits (PHYSICAL_RATIO: 0.04 < k_o/k_c < 0.8, thickness >= MIN_COAT_PX)
    count: a coated fit with no contrast between the layers is the single layer fitting
    noise.  When the decision is borderline, ``COAT_EXTRA_STARTS`` more starts are tried.
    The decision compares LM solutions (``_Fitter.polish`` notes that LM stops short of the
    optimum, a layered fit further than a single one: the test errs towards no layer).
    ``blur_room`` False: every thickness of the grid is tried, whatever the blur (the fringe
    correction's coated alternative, ``silhouette_fit``).
    Returns (state or None, iterations, coating-test dict)."""
    K = f1.K
    cost1 = st1.cost
    c1, sg1, _, _, _ = f1.unpack(st1.v)
    if coat_hint:
        cands = [float(np.clip(coat_hint, 0.6, max_coat * 0.95))]
    else:
        room = COAT_PER_BLUR * sg1 if blur_room else np.inf
        cands = [t for t in COAT_GRID_PX if t <= min(max_coat * 0.95, room)]
    test = {"model": "single", "threshold": COAT_DCHI2, "candidates_px": list(cands)}
    if not cands:
        test["skipped"] = "no room for a layer >= 1.5 px in the single-layer blur"
        return None, 0, test

    starts = [_coated_start(f1, st1, lim2, t) for t in cands]
    order, runs, n_it = _first_runs(f2, starts, cost1, lim2, max_iter)
    bp = _best_physical(f2, runs)
    gain = cost1 - bp.cost if bp is not None else -np.inf
    if not coat_hint and (bp is None or -3 * COAT_DCHI2 < gain <= COAT_DCHI2):
        # borderline: a layer neither found nor clearly excluded (or none physical yet); a
        # physical layer found worse than the single layer may be a local minimum (the thin
        # oxides missed at coarse pixels and low SNR ended at -13 to -26)
        bp, it = _more_starts(f2, starts, order, runs, bp, cost1, lim2, max_iter)
        n_it += it
    if coat_hint:
        bp = min(runs, key=lambda r: r.cost)
    if bp is None:
        test["physical"] = False
        return None, n_it, test
    # a start that won after its first iterations: converged like the single-layer fit
    bp, it = _converge(f2, bp, cost1, lim2, max_iter)
    n_it += it
    _, _, ko2, kc2, coat2 = f2.unpack(bp.v)
    gain = float(st1.cost - bp.cost)
    # outward shift of the coated model's outer edge relative to the single layer's
    shift = float(np.mean(bp.v[:K] - c1))
    test.update(
        dchi2=gain,
        physical=_physical(f2, bp),
        thickness_px=float(coat2),
        contrast_ratio=float(ko2 / kc2),
        outer_shift_px=shift,
    )
    if coat_hint or (gain > COAT_DCHI2 and _physical(f2, bp)):
        test["model"] = "coated"
    else:
        n_it += _ambiguous_layer(f2, runs, bp, gain, (c1, K), cost1, lim2, max_iter, test)
    return bp, n_it, test


def _physical(f2, st):
    """A layer that counts: k_o/k_c within PHYSICAL_RATIO and thickness >= MIN_COAT_PX."""
    _, _, ko, kc, coat = f2.unpack(st.v)
    lo, hi = PHYSICAL_RATIO
    return bool(lo * kc < ko < hi * kc and coat >= MIN_COAT_PX)


def _best_physical(f2, runs):
    ph = [r for r in runs if _physical(f2, r)]
    return min(ph, key=lambda r: r.cost) if ph else None


def _first_runs(f2, starts, cost1, lim2, max_iter):
    """(order of the starts by cost, runs, iterations): the two best starts get COAT_START_ITERS
    full LM iterations (the second only if the first is no clear layer), the better is converged."""
    order = np.argsort([f2.evaluate(v).cost for v in starts])
    n_it = 0
    runs = []
    for j in order[:2]:
        st, _, _, it = f2.run(starts[j], "full", COAT_START_ITERS, *lim2)
        n_it += it
        runs.append(st)
        if cost1 - st.cost > 3 * COAT_DCHI2 and _physical(f2, st):
            break  # a clear layer from the best-ranked start: the second is not needed
    st, it = _converge(f2, min(runs, key=lambda r: r.cost), cost1, lim2, max_iter)
    n_it += it
    runs.append(st)
    return order, runs, n_it


def _more_starts(f2, starts, order, runs, bp, cost1, lim2, max_iter):
    """(best physical run, iterations) after COAT_EXTRA_STARTS more starts (appended to ``runs``),
    the best physical one converged if it beats ``bp``."""
    n_it = 0
    for j in order[2 : 2 + COAT_EXTRA_STARTS]:
        st, _, _, it = f2.run(starts[j], "full", COAT_START_ITERS, *lim2)
        n_it += it
        runs.append(st)
    nb = _best_physical(f2, runs)
    if nb is not None and (bp is None or nb.cost < bp.cost):
        st, it = _converge(f2, nb, cost1, lim2, max_iter)
        n_it += it
        runs.append(st)
    return _best_physical(f2, runs), n_it


def _ambiguous_layer(f2, runs, bp, gain, single, cost1, lim2, max_iter, test):
    """Light layers that fit about as well as none are neither found nor excluded: the edge may
    lie as far out as the largest of them puts it (``test`` gets ambiguous_*).  Returns the
    iterations spent converging near ones."""
    c1, K = single
    n_it = 0

    def shift_of(r):
        return float(np.mean(r.v[:K] - c1))

    alike = [r for r in runs if _physical(f2, r) and cost1 - r.cost > -COAT_DCHI2 and shift_of(r) > 0.25]
    if _physical(f2, bp) and gain > -COAT_DCHI2 and shift_of(bp) > 0.25:
        alike.append(bp)
    if alike:
        # thicker layers stopped after their start iterations just outside the threshold
        # may reach it when converged: the largest shift needs them
        reach = max(shift_of(r) for r in alike)
        near = [
            r
            for r in runs
            if _physical(f2, r) and -3 * COAT_DCHI2 < cost1 - r.cost <= -COAT_DCHI2 and shift_of(r) > reach
        ]
        for r in sorted(near, key=shift_of, reverse=True)[:2]:
            st, it = _converge(f2, r, cost1, lim2, max_iter)
            n_it += it
            if _physical(f2, st) and cost1 - st.cost > -COAT_DCHI2 and shift_of(st) > 0.25:
                alike.append(st)
        far = max(alike, key=shift_of)
        _, _, ko_f, kc_f, coat_f = f2.unpack(far.v)
        test.update(
            ambiguous=True,
            ambiguous_shift_px=shift_of(far),
            ambiguous_thickness_px=float(coat_f),
            ambiguous_dchi2=float(cost1 - far.cost),
        )
    return n_it
