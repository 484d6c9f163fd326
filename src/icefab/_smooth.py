"""Compiled smoothing of uniformly resampled polylines within a tolerance (thesis 4.1.1:
"local polynomial regression or cubic smoothing splines").

Shared by the motion stage (:mod:`icefab._mtts` smooths every PATHSPLIT piece within
``motion.smoothing_tolerance_mm``) and the geometry stage (:func:`icefab.geometry.smooth_rings`
smooths fill rings in the paths stage), so both stay one kernel.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: The same fast-math flags as :mod:`icefab._mtts` (see there: no "reassoc"/"contract", so
#: a freshly compiled kernel and the cached one round alike).
_FM = {"nsz", "arcp"}


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _turn_within(cturn, k, w, n, max_turn):  # pragma: no cover - compiled
    """Whether the grid turns by at most ``max_turn`` (rad) within the half-width ``w``
    (grid points) round grid point ``k`` of a piece of ``n``, given its cumulated turning
    ``cturn`` (:func:`smooth_pieces`)."""
    ka = max(int(math.ceil(k - w - 1e-9)), 0)
    kb = min(int(math.floor(k + w + 1e-9)), n - 1)
    return cturn[kb] - cturn[min(ka + 1, kb)] <= max_turn


@njit(cache=True, fastmath=_FM, error_model="numpy")
def smooth_pieces(gstart, graw, h, fstart, fu, fraw, sigma_pts, tol, max_turn):
    """Optional smoothing of resampled pieces (thesis 4.1.1: "local polynomial regression
    or cubic smoothing splines").

    The curve is a local quadratic regression along s through the uniformly resampled
    points of each piece, with biweight weights (1 - (t / w)^2)^2 over a half-width w of
    3 sigma_pts grid points, kept symmetric near the ends (piece ends stay put) and
    narrowed where the grid turns by more than ``max_turn`` rad within it (so small
    circles are not shrunk); w is interpolated between grid points and the weights vanish
    at the window's edge, so the curve is continuous in s. A quadratic fit keeps circles
    and lines in place and rounds polyline vertices. It is evaluated at every point of
    the followed polyline: the grid points and the input's own vertices (a fine input
    stays fine and a coarse polygon's vertices land on the curve). Each displacement is
    scaled by a factor <= min(1, tol / |d|) at every point, smooth along s (running
    minimum and moving average over +-sigma on the grid, interpolated between grid
    points): every point moves by at most ``tol`` mm, and so does every chord (both ends
    of a chord lie on one input segment).

    gstart (P+1,) int64, graw (G, 2) mm: the resampled grid; h (P,) mm grid spacing;
    fstart (P+1,) int64, fu (F,) mm piece-local arc length, fraw (F, 2) mm: the followed
    points on the input path. Returns the smoothed followed points (F, 2).
    """
    out = fraw.copy()
    P = gstart.shape[0] - 1
    r = 3.0 * sigma_pts
    rr = max(1, int(sigma_pts + 0.5))
    nmax = 0
    gmax = 0
    for p in range(P):
        nmax = max(nmax, fstart[p + 1] - fstart[p])
        gmax = max(gmax, gstart[p + 1] - gstart[p])
    d = np.zeros((nmax, 2))
    fv = np.ones(nmax)
    cturn = np.zeros(gmax + 1)
    rwk = np.zeros(gmax)
    fg = np.ones(gmax)
    g1 = np.ones(gmax)
    g2 = np.ones(gmax)
    cnt = np.zeros(gmax + 1, np.int64)   # running count of factors under 1
    # at a grid point with an integer half-width R the fit is a fixed symmetric filter:
    # fitted value = sum_t ker[R, t + R] y[k + t] (m1 = m3 = 0: c12 = 0), precomputed
    rmax = int(r) + 1
    ker = np.zeros((rmax + 1, 2 * rmax + 1))
    for R in range(2, rmax + 1):
        m0 = m2 = m4 = 0.0
        for t in range(-R + 1, R):
            q = 1.0 - (t / R) ** 2
            w = q * q
            m0 += w
            m2 += w * t * t
            m4 += w * t ** 4
        det = m0 * m4 - m2 * m2
        for t in range(-R + 1, R):
            q = 1.0 - (t / R) ** 2
            ker[R, t + R] = q * q * (m4 - m2 * t * t) / det
    for p in range(P):
        i0 = gstart[p]
        n = gstart[p + 1] - i0
        j0 = fstart[p]
        nf = fstart[p + 1] - j0
        hp = h[p]
        # cumulated turning of the grid polyline: cturn[k] = sum of |turn| at 1..k-1
        cturn[0] = 0.0
        cturn[1] = 0.0
        for k in range(1, n - 1):
            ax = graw[i0 + k, 0] - graw[i0 + k - 1, 0]
            ay = graw[i0 + k, 1] - graw[i0 + k - 1, 1]
            bx = graw[i0 + k + 1, 0] - graw[i0 + k, 0]
            by = graw[i0 + k + 1, 1] - graw[i0 + k, 1]
            cturn[k + 1] = cturn[k] + abs(math.atan2(ax * by - ay * bx, ax * bx + ay * by))
        # window half-width per grid point (grid points)
        # the widest of w0, w0 - 1, ... (> 0) within which the grid turns by at most
        # max_turn, else 0: the turn within a window shrinks with it (cturn never
        # decreases), so a bisection finds the step the walk down from w0 stops at (the
        # same value: w0 - j is exact) where that walk took up to 3 sigma_pts steps
        for k in range(n):
            w0 = min(r, float(k), float(n - 1 - k))
            w = w0
            if w0 > 0.0 and not _turn_within(cturn, k, w0, n, max_turn):
                lo = 1
                hi = int(math.ceil(w0))   # w0 - hi <= 0: the walk's end
                while lo < hi:
                    mid = (lo + hi) // 2
                    if _turn_within(cturn, k, w0 - mid, n, max_turn):
                        hi = mid
                    else:
                        lo = mid + 1
                w = w0 - lo
            rwk[k] = max(w, 0.0)
        for k in range(n):
            fg[k] = 1.0
        for jj in range(nf):
            d[jj, 0] = 0.0
            d[jj, 1] = 0.0
            fv[jj] = 1.0
            pos = fu[j0 + jj] / hp
            k0 = min(max(int(pos), 0), n - 2)
            t0 = pos - k0
            rw = (1.0 - t0) * rwk[k0] + t0 * rwk[k0 + 1]
            rw = min(rw, pos, (n - 1) - pos)
            kg = int(pos + 0.5)
            R = int(rw + 0.5)
            if (rw >= 2.0 and abs(pos - kg) < 1e-9 and abs(rw - R) < 1e-9
                    and kg - R + 1 >= 0 and kg + R - 1 <= n - 1):
                fx = 0.0
                fy = 0.0
                for t in range(-R + 1, R):
                    c = ker[R, t + R]
                    fx += c * graw[i0 + kg + t, 0]
                    fy += c * graw[i0 + kg + t, 1]
                dx = fx - fraw[j0 + jj, 0]
                dy = fy - fraw[j0 + jj, 1]
                d[jj, 0] = dx
                d[jj, 1] = dy
                dd = math.sqrt(dx * dx + dy * dy)
                if dd > tol:
                    fv[jj] = tol / dd
            elif rw >= 2.0:
                a = max(int(math.floor(pos - rw)) + 1, 0)
                b = min(int(math.ceil(pos + rw)) - 1, n - 1)
                # weighted normal equations of y = c0 + c1 t + c2 t^2, t = k - pos
                m0 = m1 = m2 = m3 = m4 = 0.0
                sx0 = sx1 = sx2 = sy0 = sy1 = sy2 = 0.0
                for k in range(a, b + 1):
                    t = k - pos
                    q = 1.0 - (t / rw) ** 2
                    if q <= 0.0:
                        continue
                    w = q * q
                    t2 = t * t
                    m0 += w
                    m1 += w * t
                    m2 += w * t2
                    m3 += w * t2 * t
                    m4 += w * t2 * t2
                    x = graw[i0 + k, 0]
                    y = graw[i0 + k, 1]
                    sx0 += w * x
                    sx1 += w * t * x
                    sx2 += w * t2 * x
                    sy0 += w * y
                    sy1 += w * t * y
                    sy2 += w * t2 * y
                c11 = m2 * m4 - m3 * m3
                c12 = m2 * m3 - m1 * m4
                c13 = m1 * m3 - m2 * m2
                det = m0 * c11 + m1 * c12 + m2 * c13
                if abs(det) > 1e-12 * max(m0 * m2 * m4, 1e-300):
                    dx = (c11 * sx0 + c12 * sx1 + c13 * sx2) / det - fraw[j0 + jj, 0]
                    dy = (c11 * sy0 + c12 * sy1 + c13 * sy2) / det - fraw[j0 + jj, 1]
                    d[jj, 0] = dx
                    d[jj, 1] = dy
                    dd = math.sqrt(dx * dx + dy * dy)
                    if dd > tol:
                        fv[jj] = tol / dd
            # fold the factor bound into both grid ends of the segment holding the point
            if fv[jj] < fg[k0]:
                fg[k0] = fv[jj]
            if fv[jj] < fg[k0 + 1]:
                fg[k0 + 1] = fv[jj]
        # running minimum, then moving average, both over +-rr grid points: every averaged
        # value is a minimum over a window containing the point, so g2 <= fg
        full = True
        for k in range(n):
            if fg[k] < 1.0:
                full = False
                break
        if full:  # no displacement is scaled on this piece
            for jj in range(nf):
                out[j0 + jj, 0] = fraw[j0 + jj, 0] + d[jj, 0]
                out[j0 + jj, 1] = fraw[j0 + jj, 1] + d[jj, 1]
            continue
        # (a window of factors all 1 has minimum 1 and sum b - a, exactly: the scaled
        # stretches are short, and skipping the loops over the others took 15 % off the
        # paths stage's smoothing, the same values to the last bit; BENCHMARKS.md)
        cnt[0] = 0
        for k in range(n):
            cnt[k + 1] = cnt[k] + (1 if fg[k] < 1.0 else 0)
        for k in range(n):
            a = max(0, k - rr)
            b = min(n, k + rr + 1)
            mn = 1.0
            if cnt[b] > cnt[a]:
                for kk in range(a, b):
                    mn = min(mn, fg[kk])
            g1[k] = mn
        cnt[0] = 0
        for k in range(n):
            cnt[k + 1] = cnt[k] + (1 if g1[k] < 1.0 else 0)
        for k in range(n):
            a = max(0, k - rr)
            b = min(n, k + rr + 1)
            if cnt[b] > cnt[a]:
                sm = 0.0
                for kk in range(a, b):
                    sm += g1[kk]
            else:
                sm = float(b - a)
            g2[k] = sm / (b - a)
        for jj in range(nf):
            pos = fu[j0 + jj] / hp
            k0 = min(max(int(pos), 0), n - 2)
            t0 = pos - k0
            sc = (1.0 - t0) * g2[k0] + t0 * g2[k0 + 1]
            out[j0 + jj, 0] = fraw[j0 + jj, 0] + sc * d[jj, 0]
            out[j0 + jj, 1] = fraw[j0 + jj, 1] + sc * d[jj, 1]
    return out


@njit(cache=True, error_model="numpy")
def periodic_pieces(pts, starts, spacing, pad_mm, min_pts, min_length):
    """Closed rings as pieces for :func:`smooth_pieces`, padded so that they wrap.

    Ring r is ``pts[starts[r]:starts[r+1]]`` (k >= 3 points, not repeated at the end), of
    perimeter L. Its grid is uniform along the ring, ``n = max(min_pts, ceil(L / spacing))``
    segments of ``h = L / n``, run ``m = min(n, ceil(pad_mm / h) + 1)`` grid points further
    at both ends (the ring goes round again), so the smoothing window of every point of
    the ring sees the ring on both sides and the pieces' fixed ends lie outside it. The
    points evaluated are the grid points and the ring's own vertices (and their wrapped
    copies in the padding), in order: two consecutive ones lie on one segment of the ring.

    Returns gstart (R+1,), graw (G, 2) mm, h (R,) mm, fstart (R+1,), fu (F,) mm from the
    piece start, fraw (F, 2) mm, own (F,) bool (the point lies in [0, L) of its ring: the
    smoothed ring is made of those). A ring shorter than ``min_length`` mm (or of no
    length) has empty pieces.
    """
    R = starts.shape[0] - 1
    nseg = np.zeros(R, np.int64)
    mpad = np.zeros(R, np.int64)
    h = np.zeros(R)
    per = np.zeros(R)
    G = 0
    F = 0
    for r in range(R):
        a = starts[r]
        b = starts[r + 1]
        L = 0.0
        for i in range(a, b):
            j = i + 1 if i + 1 < b else a
            L += math.sqrt((pts[j, 0] - pts[i, 0]) ** 2 + (pts[j, 1] - pts[i, 1]) ** 2)
        per[r] = L
        if not L >= min_length or not L > 0.0:
            continue
        n = max(min_pts, int(math.ceil(L / spacing - 1e-9)))
        h[r] = L / n
        m = min(n, int(math.ceil(pad_mm / h[r])) + 1)
        nseg[r] = n
        mpad[r] = m
        G += n + 2 * m + 1
        F += n + 2 * m + 1 + 3 * (b - a)
    gstart = np.zeros(R + 1, np.int64)
    fstart = np.zeros(R + 1, np.int64)
    graw = np.empty((G, 2))
    fu = np.empty(F)
    fraw = np.empty((F, 2))
    own = np.zeros(F, np.bool_)
    g = 0
    f = 0
    for r in range(R):
        gstart[r] = g
        fstart[r] = f
        n = nseg[r]
        if n == 0:
            continue
        a = starts[r]
        k = starts[r + 1] - a
        L = per[r]
        hr = h[r]
        m = mpad[r]
        S = np.empty(k + 1)  # arc length of each vertex, S[k] = L (back at vertex 0)
        S[0] = 0.0
        for i in range(k):
            j = a + i + 1 if i + 1 < k else a
            S[i + 1] = S[i] + math.sqrt((pts[j, 0] - pts[a + i, 0]) ** 2
                                        + (pts[j, 1] - pts[a + i, 1]) ** 2)
        lo = -m * hr
        hi = (n + m) * hr
        # the ring's vertices (wrapped copies too) inside the padded range, in order
        c = -1
        vi = 0
        while c < 2 and S[vi] + c * L < lo - 1e-12:
            vi += 1
            if vi == k:
                vi = 0
                c += 1
        for jg in range(-m, n + m + 1):
            u = jg * hr
            # vertices before this grid point (not on one)
            while c < 2:
                sv = S[vi] + c * L
                if sv >= u - 1e-9 * hr:
                    break
                if sv > lo:
                    fu[f] = sv - lo
                    fraw[f, 0] = pts[a + vi, 0]
                    fraw[f, 1] = pts[a + vi, 1]
                    own[f] = sv >= 0.0 and sv < L
                    f += 1
                vi += 1
                if vi == k:
                    vi = 0
                    c += 1
            if c < 2 and abs(S[vi] + c * L - u) <= 1e-9 * hr:  # a vertex on this grid point
                vi += 1
                if vi == k:
                    vi = 0
                    c += 1
            # the grid point: u wrapped onto [0, L), located on its segment
            w = u - math.floor(u / L) * L
            if w >= L:
                w = 0.0
            lo_i = 0
            hi_i = k
            while hi_i - lo_i > 1:
                mid = (lo_i + hi_i) // 2
                if S[mid] <= w:
                    lo_i = mid
                else:
                    hi_i = mid
            i0 = lo_i
            i1 = i0 + 1 if i0 + 1 < k else 0
            ds = S[i0 + 1] - S[i0]
            t = (w - S[i0]) / ds if ds > 0.0 else 0.0
            x = pts[a + i0, 0] + t * (pts[a + i1, 0] - pts[a + i0, 0])
            y = pts[a + i0, 1] + t * (pts[a + i1, 1] - pts[a + i0, 1])
            graw[g, 0] = x
            graw[g, 1] = y
            g += 1
            fu[f] = u - lo
            fraw[f, 0] = x
            fraw[f, 1] = y
            own[f] = jg >= 0 and jg < n
            f += 1
    gstart[R] = g
    fstart[R] = f
    return gstart, graw, h, fstart, fu[:f], fraw[:f], own[:f]


@njit(cache=True, error_model="numpy")
def collect_rings(moved, fraw, fstart, own):
    """The smoothed rings out of :func:`periodic_pieces`' padded pieces, and how far each
    ring's input reaches outside its smoothed form.

    moved (F, 2) mm: the smoothed points of every piece; fraw (F, 2) mm their input
    positions; fstart (R+1,), own (F,) as :func:`periodic_pieces` returns them. A point
    that moves into the area (against the left normal of an input segment it lies on: the
    one to the next point or the one from the previous; icefab's rings have their area on
    the left) counts with the whole length of its move, which bounds how far it lies from
    the smoothed ring; along a chord the move is linear between its ends.

    Returns (points (M, 2) mm, starts (R+1,) int64: ring r is ``points[starts[r]:
    starts[r+1]]``, reach (R,) mm: the largest such move of ring r, 0 if none, inward
    (M,) mm: each point's move if it moved into the area, else 0).
    """
    R = fstart.shape[0] - 1
    M = 0
    for i in range(own.shape[0]):
        if own[i]:
            M += 1
    pts = np.empty((M, 2))
    starts = np.zeros(R + 1, np.int64)
    reach = np.zeros(R)
    inward = np.zeros(M)
    m = 0
    for r in range(R):
        starts[r] = m
        a = fstart[r]
        b = fstart[r + 1]
        for i in range(a, b):
            if not own[i]:
                continue
            pts[m, 0] = moved[i, 0]
            pts[m, 1] = moved[i, 1]
            m += 1
            dx = moved[i, 0] - fraw[i, 0]
            dy = moved[i, 1] - fraw[i, 1]
            if dx == 0.0 and dy == 0.0:
                continue
            into = False
            for j in (i - 1, i + 1):
                if j < a or j >= b:
                    continue
                sx = fraw[max(i, j), 0] - fraw[min(i, j), 0]
                sy = fraw[max(i, j), 1] - fraw[min(i, j), 1]
                if dy * sx - dx * sy > 0.0:  # d . (-sy, sx) > 0: into the left side
                    into = True
            if into:
                inward[m - 1] = math.sqrt(dx * dx + dy * dy)
                reach[r] = max(reach[r], inward[m - 1])
    starts[R] = m
    return pts, starts, reach, inward
