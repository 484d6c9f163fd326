"""Compiled kernels of minimum-time trajectory shaping (thesis 4.1-4.2).

Private to :mod:`icefab.motion`. Everything works on flat arrays holding many *pieces*
(sub-paths between split corners, each starting and ending at rest), so a whole layer is
one call: ``gstart (P+1,) int64`` gives piece p the grid points ``gstart[p]:gstart[p+1]``
of a uniform grid along s with spacing ``h[p]`` mm.

State along s is the speed ``v`` (mm/s); between two grid points the tangential
acceleration is constant (``v^2`` linear in s), which is also how the samples at constant
dt are taken, so the sampled trajectory is exactly the planned one.

Constraints at grid point i (x = v^2, u = tangential acceleration, p(s) the path,
q(s) the joints; thesis eqs. 4.3-4.5, 4.8, 4.10):

* Cartesian speed:  x <= vcap^2
* total acceleration: u^2 + (|p''| x)^2 <= A^2            (eq. 4.8: tangential + radial)
* joint speed:       |q'_j| sqrt(x) <= qv_j
* joint acceleration: |q'_j u + q''_j x| <= qa_j          (like TOPP-RA's per-point rows)
* jerk (VCON envelope): |p'''| v^3 <= J, |q'''_j| v^3 <= qj_j  (eqs. 4.4-4.5)

Degenerate cases: a piece always has >= 3 grid points (>= 2 segments) so its interior
moves; a joint with |q'_j| ~ 0 gives no bound on u (only on x through q''_j).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from icefab._smooth import smooth_pieces

_EPS = 1e-12
#: LLVM fast-math flags that keep inf and NaN semantics (unbounded joints use inf) and the
#: order of every sum: with "reassoc" or "contract" a kernel compiled in the running process
#: and the same kernel loaded from numba's cache rounded differently, so the trajectories
#: of one input depended on whether the cache existed (a bunny layer: 4 of 466 trajectories
#: one sample apart); without them they agree, MTTS 5 % slower (no fast-math: 10 %).
_FM = {"nsz", "arcp"}


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _derivs(y, i0, i1, h, w, d1, d2, d3):
    """First, second and third derivatives along s of y[i0:i1] (k, c) by finite
    differences on the uniform grid of spacing h; ends copy their neighbours.

    The third derivative is the slope of the second derivative averaged over 2w+1 grid
    points (``JERK_WINDOW_MM``): polylines from a slicer turn at every vertex, and a
    third difference at the grid spacing would see each vertex as a jerk spike.
    """
    n = i1 - i0
    c = y.shape[1]
    for k in range(c):
        for i in range(i0, i1):
            if i == i0:
                d1[i, k] = (y[i + 1, k] - y[i, k]) / h
            elif i == i1 - 1:
                d1[i, k] = (y[i, k] - y[i - 1, k]) / h
            else:
                d1[i, k] = (y[i + 1, k] - y[i - 1, k]) / (2.0 * h)
        for i in range(i0 + 1, i1 - 1):
            d2[i, k] = (y[i + 1, k] - 2.0 * y[i, k] + y[i - 1, k]) / (h * h)
        d2[i0, k] = d2[i0 + 1, k] if n > 2 else 0.0
        d2[i1 - 1, k] = d2[i1 - 2, k] if n > 2 else 0.0
        # slope of the moving average of d2 over [i-w, i+w]: with clamped indices this
        # is (d2[i+w] + d2[i+w+1] - d2[i-w] - d2[i-w-1]) / ((2w+1) 2h)
        den = (2.0 * w + 1.0) * 2.0 * h
        last = i1 - 1
        for i in range(i0, i1):
            a1 = min(i + w, last)
            a2 = min(i + w + 1, last)
            b1 = max(i - w, i0)
            b2 = max(i - w - 1, i0)
            d3[i, k] = (d2[a1, k] + d2[a2, k] - d2[b1, k] - d2[b2, k]) / den


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _accel_interval(i, x, sign, kap, kv, kvq, qd1, qd2, A, qa):
    """[lo, hi] of the tangential acceleration at grid point i and x = v^2.

    sign = +1 going forward along s, -1 going backward (joint rates change sign). kv,
    kvq (., m): the share of the total and of each joint's acceleration a polyline
    vertex's own turn takes near it, per mm/s of speed (_vertex_bounds).
    """
    cen = kap[i] * x
    if kv[i] > 0.0:  # a polyline vertex: its acceleration grows like v (_vertex_bounds)
        cen = max(cen, kv[i] * math.sqrt(x))
    r = A * A - cen * cen
    am = math.sqrt(r) if r > 0.0 else 0.0
    lo = -am
    hi = am
    for j in range(qd1.shape[1]):
        if not math.isfinite(qa[j]):
            continue
        d1 = sign * qd1[i, j]
        if abs(d1) < 1e-9:
            continue
        d2x = qd2[i, j] * x
        qaj = qa[j]
        if kvq[i, j] > 0.0:   # a vertex's turn nearby takes its share (_vertex_bounds)
            qaj = max(qaj - kvq[i, j] * math.sqrt(x), 0.0)
        a = (-qaj - d2x) / d1
        b = (qaj - d2x) / d1
        if a > b:
            a, b = b, a
        if a > lo:
            lo = a
        if b < hi:
            hi = b
    return lo, hi


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _cubic_root(j0, a0, v0, ds):
    """The positive root of j0 t^3/6 + a0 t^2/2 + v0 t - ds = 0 (thesis eq. 4.7).

    With j0 > 0, a0 >= 0, v0 >= 0, ds > 0 the cubic is increasing and convex on t > 0,
    so exactly one root is positive (the thesis' argument). From rest (v0 = a0 = 0) it
    is explicit, cbrt(6 ds / j0); otherwise Newton's method started from an upper bound
    (the time each positive term alone needs to reach ds) converges monotonically from
    above (convexity), in 2-5 steps to 1e-12 relative; measured faster than Cardano's
    formula (cube roots and arccos) in the passes.
    """
    if v0 <= 0.0 and a0 <= 0.0:
        return np.cbrt(6.0 * ds / j0)
    t = ds / v0 if v0 > 0.0 else np.inf
    if a0 > 0.0:
        t = min(t, math.sqrt(2.0 * ds / a0))
    # the jerk's term too: from rest with a0 = 1e-12 the bound above was 4e5 s, which
    # Newton (a third off per step that far out) left at 120 s after 20 steps, and the
    # curve jumped to full speed in one grid step
    t = min(t, np.cbrt(6.0 * ds / j0))
    for _ in range(20):
        f = ((j0 * t / 6.0 + 0.5 * a0) * t + v0) * t - ds
        fp = (0.5 * j0 * t + a0) * t + v0
        step = f / fp
        t -= step
        if step <= 1e-12 * t:
            break
    return t


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _pass(v, env, i0, i1, step, h, kap, kv, kvq, qd1, qd2, A, qa, jeff, jerk_on, a_start,
          a_rest_cap):
    """ACON (thesis 4.1.3, Fig. 4-5): an acceleration-limited (and, with jerk on,
    jerk-limited) curve from rest at the first point, and from every point where the
    profile leaves the envelope ``env``. step = +1 forward, -1 backward (deceleration
    curves are acceleration curves run backward). ``a_rest_cap`` bounds the acceleration
    of the step from rest: the joints' bounds with their rates at the rest point itself,
    which the grid's differences underestimate near a singularity. Writes into v."""
    if step > 0:
        a, b = i0, i1 - 1
    else:
        a, b = i1 - 1, i0
    sign = 1.0 if step > 0 else -1.0
    v[a] = 0.0
    acur = a_start
    i = a
    while i != b:
        nxt = i + step
        vi = v[i]
        if env[nxt] <= vi:
            # the curve never slows down (hi >= 0 below), so it is capped by the envelope
            # whatever the interval: skip it (on the envelope's flat and falling parts)
            v[nxt] = env[nxt]
            acur = (env[nxt] * env[nxt] - vi * vi) / (2.0 * h)
            i = nxt
            continue
        lo, hi = _accel_interval(i, vi * vi, sign, kap, kv, kvq, qd1, qd2, A, qa)
        if i == a and hi > a_rest_cap:
            hi = a_rest_cap
        if hi < 0.0:
            hi = 0.0
        if jerk_on and math.isfinite(jeff[i]):
            a0 = acur if acur > 0.0 else 0.0
            if a0 > hi:
                a0 = hi
            if hi > _EPS:
                ta = (-vi + math.sqrt(vi * vi + 2.0 * hi * h)) / hi
                # the jerk-limited curve covers h within ta: the acceleration bound rules
                # and the cubic need not be solved
                jfast = ((jeff[i] * ta / 6.0 + 0.5 * a0) * ta + vi) * ta >= h
            else:
                ta = np.inf
                jfast = False
            if jfast:
                ts = 0.0
            else:
                ts = _cubic_root(jeff[i], a0, vi, h)
            if ts >= ta:
                vn = vi + a0 * ts + 0.5 * jeff[i] * ts * ts
                an = a0 + jeff[i] * ts
            else:
                vn = math.sqrt(vi * vi + 2.0 * hi * h)
                an = hi
        else:
            vn = math.sqrt(vi * vi + 2.0 * hi * h)
            an = hi
        if vn >= env[nxt]:
            vn = env[nxt]
            an = (vn * vn - vi * vi) / (2.0 * h)
        v[nxt] = vn
        acur = an
        i = nxt


#: Accelerations (mm/s^2) JCON takes as none when it looks for a change of sign: an
#: envelope flat but for rounding (a gantry's axis speed over the axis' rate along the
#: path, 1 +- 1e-16) gives accelerations of ~1e-8 mm/s^2 of either sign.
ACC_ZERO_MM_S2 = 1e-6


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _opposite(a, b):
    """Whether accelerations a and b (mm/s^2) have opposite signs, both beyond
    ``ACC_ZERO_MM_S2``."""
    return a * b < 0.0 and abs(a) > ACC_ZERO_MM_S2 and abs(b) > ACC_ZERO_MM_S2


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _jcon(v, i0, i1, h, jeff, tol):
    """JCON (thesis 4.1.4, Fig. 4-6, eq. 4.12): where the speed-decrease jerk exceeds
    ``jeff*(1+tol)``, grow an interval (each side stops at a change of acceleration sign
    or at the piece ends) until the acceleration change across it respects the bound, and
    replace the speeds inside by the cubic velocity polynomial of eq. 4.12 (only ever
    lowering them, so durations only grow). Returns the number of intervals smoothed."""
    n = i1 - i0
    if n < 5:
        return 0
    t = np.empty(n)
    acc = np.empty(n)
    t[0] = 0.0
    for k in range(1, n):
        vs = v[i0 + k - 1] + v[i0 + k]
        t[k] = t[k - 1] + (2.0 * h / vs if vs > 1e-9 else 1e9)
    for k in range(n):
        km = k - 1 if k > 0 else 0
        kp = k + 1 if k < n - 1 else n - 1
        acc[k] = (v[i0 + kp] ** 2 - v[i0 + km] ** 2) / (2.0 * h * (kp - km))
    count = 0
    k = 1
    while k < n - 1:
        jk = jeff[i0 + k]
        dtk = t[k + 1] - t[k - 1]
        if (dtk <= 0.0 or not math.isfinite(jk)
                or (acc[k + 1] - acc[k - 1]) / dtk > -jk * (1.0 + tol)):
            k += 1
            continue
        lft = k - 1
        rgt = k + 1
        fl = True
        fr = True
        while True:
            jt = (acc[lft] - acc[rgt]) / (t[rgt] - t[lft])
            if jt < jk or not (fl or fr):
                break
            if fl:
                if lft <= 1 or _opposite(acc[lft - 1], acc[lft]):
                    fl = False
                else:
                    lft -= 1
            if fr:
                if rgt >= n - 2 or _opposite(acc[rgt + 1], acc[rgt]):
                    fr = False
                else:
                    rgt += 1
        # eq. 4.12: v(tau) = D tau^3 + C tau^2 + B tau + A over the interval
        dT = t[rgt] - t[lft]
        va = v[i0 + lft]
        vb = v[i0 + rgt]
        cA = va
        cB = acc[lft] * dT
        cC = 3.0 * vb - acc[rgt] * dT - 3.0 * cA - 2.0 * cB
        cD = vb - cA - cB - cC
        for m in range(lft + 1, rgt):
            tau = (t[m] - t[lft]) / dT
            vp = ((cD * tau + cC) * tau + cB) * tau + cA
            if 0.0 < vp < v[i0 + m]:
                v[i0 + m] = vp
        count += 1
        k = rgt
    return count


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _accel_bound_x(k0, k1, d2, qd2, n, i, A, qa):
    """Largest v^2 allowed by the total and joint accelerations at zero tangential
    acceleration, with second derivatives averaged over points [i-k, i+k] (prefix sums
    d2 (n+1, 2), qd2 (n+1, m))."""
    a = max(i - k0, 0)
    b = min(i + k1, n - 1) + 1
    cnt = b - a
    cx = (d2[b, 0] - d2[a, 0]) / cnt
    cy = (d2[b, 1] - d2[a, 1]) / cnt
    kap = math.sqrt(cx * cx + cy * cy)
    x = A / kap if kap > _EPS else np.inf
    for j in range(qd2.shape[1]):
        if math.isfinite(qa[j]):
            c = abs(qd2[b, j] - qd2[a, j]) / cnt
            if c > _EPS:
                x = min(x, qa[j] / c)
    return x


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _step_curvature(n, h, vcap, dt, A, qa, p2, qd2, c2, cq):
    """Second derivatives as the robot sees them: averaged over one output step.

    The robot receives one point every dt; between two samples it moves v dt along the
    path, so the acceleration it is commanded (the second difference of the samples over
    dt^2) is the turning over a step's length, not the turning at one 0.4 mm grid point.
    A polyline vertex turning by alpha is therefore no 0.4 mm-radius curve: at speed v it
    costs v alpha / dt. Here p2 and qd2 (rows 0..n-1) are replaced in place by their
    averages over the widest centred window W = (2k+1) h that the speed allowed with that
    window still covers in one step (v dt >= W); on a smooth curve every window gives the
    same value, at a vertex the turning is spread over the step. In: p2 (., 2) and
    qd2 (., m) raw second differences; c2, cq work arrays (n+1, .).
    """
    kmax = int((vcap * dt / h - 1.0) * 0.5)
    if kmax <= 0:
        return
    for c in range(2):
        c2[0, c] = 0.0
        for i in range(n):
            c2[i + 1, c] = c2[i, c] + p2[i, c]
    for c in range(qd2.shape[1]):
        cq[0, c] = 0.0
        for i in range(n):
            cq[i + 1, c] = cq[i, c] + qd2[i, c]
    for i in range(n):
        best = 0
        for k in range(1, kmax + 1):
            x = _accel_bound_x(k, k, c2, cq, n, i, A, qa)
            wk = (2 * k + 1) * h
            if x * dt * dt >= wk * wk:
                best = k
            else:
                break
        if best > 0:
            a = max(i - best, 0)
            b = min(i + best, n - 1) + 1
            cnt = b - a
            p2[i, 0] = (c2[b, 0] - c2[a, 0]) / cnt
            p2[i, 1] = (c2[b, 1] - c2[a, 1]) / cnt
            for c in range(qd2.shape[1]):
                qd2[i, c] = (cq[b, c] - cq[a, c]) / cnt


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _vertex_bounds(sv, tau, jac, n, h, vcap, dt, A, qa, xk, kv, kvq, ctau):
    """Speed bounds from the vertices of the polyline actually followed (v^2 into xk[0:n]).

    The robot gets one sample every dt, a step of L = v dt along the path. The second
    difference of three samples centred on a point turns by the chord directions' change,
    which is the sum of the vertices' unit-tangent changes tau_w weighted by the triangle
    (1 - |d_w| / L) over d_w in (-L, L) (d_w: arc-length distance). Its acceleration is
    |a v - c / dt| / dt with a = sum tau_w and c = sum tau_w |d_w| over the vertices
    within L, so the largest v with acceleration <= A is the larger root of a quadratic;
    vertices are added nearest first until the root's L no longer reaches the next one.
    The bound (worst case: a sample on the vertex) is applied at the two grid points around
    each vertex. On a finely sampled curve of curvature kappa this gives v^2 kappa <= A; at
    a polyline vertex turning by alpha it gives v alpha / dt <= A, which the grid
    curvature misses when the samples are denser than the 0.4 mm grid.

    The joints see the same turn through their Jacobian at the vertex (jac (n, m, 2), at
    the grid points: the nearest one's):
    |J_j (a v - c / dt)| / dt <= qa_j bounds v too (linear in v), and kvq (n, m) reserves
    each joint's share as kv does the total's. Without it a tour's travel curve near the
    SCARA's full reach turned 32-43 degrees between two samples at 1.4 times joint 2's
    bound, which no re-plan under lower joint bounds changed (hunt Q).
    """
    m = qa.shape[0]
    for i in range(n):
        xk[i] = np.inf
        kv[i] = 0.0
        for j in range(m):
            kvq[i, j] = 0.0
    K = sv.shape[0]
    # prefix sums of |tau| and |tau| s (ctau (K+1, 2) work array): the acceleration at
    # speed v is at most sum |tau_w| (v - |d_w| / dt) / dt over the vertices within v dt,
    # which grows with v: where it stays under A at vcap the bound is vcap (smooth
    # polylines), found without growing the window
    ctau[0, 0] = 0.0
    ctau[0, 1] = 0.0
    for w in range(K):
        ta = math.sqrt(tau[w, 0] ** 2 + tau[w, 1] ** 2)
        ctau[w + 1, 0] = ctau[w, 0] + ta
        ctau[w + 1, 1] = ctau[w, 1] + ta * sv[w]
    L0 = vcap * dt
    wl = 0
    wr = 0
    for v in range(K):
        ax = tau[v, 0]
        ay = tau[v, 1]
        if ax == 0.0 and ay == 0.0:
            continue
        while sv[v] - sv[wl] >= L0:
            wl += 1
        if wr < v:
            wr = v
        while wr + 1 < K and sv[wr + 1] - sv[v] < L0:
            wr += 1
        # sum over the window of |tau_w| (vcap - |d_w| / dt) / dt, the acceleration bound
        sl = ctau[v, 0] - ctau[wl, 0]
        sr = ctau[wr + 1, 0] - ctau[v, 0]
        dsum = (sv[v] * sl - (ctau[v, 1] - ctau[wl, 1])
                + (ctau[wr + 1, 1] - ctau[v, 1]) - sv[v] * sr)
        turn = vcap * (sl + sr) - dsum / dt   # the window's turning at vcap, times dt
        smooth = turn <= A * dt * (1.0 - 1e-9)
        gv = min(max(int(sv[v] / h + 0.5), 0), n - 1)   # the Jacobian's grid point
        for j in range(m):   # and each joint's, through its Jacobian at the vertex
            if smooth and math.isfinite(qa[j]):
                nj = math.sqrt(jac[gv, j, 0] ** 2 + jac[gv, j, 1] ** 2)
                smooth = nj * turn <= qa[j] * dt * (1.0 - 1e-9)
        if smooth:
            if L0 > 0.0:  # u = vcap: only the share reserved in kv, kvq (below)
                kvu = (ctau[v + 1, 0] - ctau[v, 0]) / dt
                c = kvu / L0
                g0 = max(0, int((sv[v] - L0) / h))
                g1 = min(n - 1, int((sv[v] + L0) / h) + 1)
                for gi in range(g0, g1 + 1):
                    val = kvu - c * abs(gi * h - sv[v])
                    if val > kv[gi]:
                        kv[gi] = val
                _joint_share(v, sv, tau, jac, gv, qa, L0, n, h, dt, kvq)
            continue
        cx = 0.0
        cy = 0.0
        lft = v - 1
        rgt = v + 1
        while True:
            al = ax * ax + ay * ay
            be = (ax * cx + ay * cy) / dt
            ga = (cx * cx + cy * cy) / (dt * dt) - A * A * dt * dt
            disc = be * be - al * ga
            if al > 1e-30 and disc >= 0.0:
                u = (be + math.sqrt(disc)) / al
            elif al <= 1e-30:
                u = np.inf
            else:
                u = 0.0
            for j in range(m):   # |alpha u - gamma| <= qa_j dt, alpha = J_j a
                if not math.isfinite(qa[j]):
                    continue
                aj = jac[gv, j, 0] * ax + jac[gv, j, 1] * ay
                if abs(aj) <= 1e-15:
                    continue
                gj = (jac[gv, j, 0] * cx + jac[gv, j, 1] * cy) / dt
                uj = ((gj if aj > 0.0 else -gj) + qa[j] * dt) / abs(aj)
                u = min(u, max(uj, 0.0))
            dl = sv[v] - sv[lft] if lft >= 0 else np.inf
            dr = sv[rgt] - sv[v] if rgt < K else np.inf
            dn = min(dl, dr)
            if u * dt <= dn or dn >= vcap * dt:
                break
            if dl <= dr:
                ax += tau[lft, 0]
                ay += tau[lft, 1]
                cx += tau[lft, 0] * dl
                cy += tau[lft, 1] * dl
                lft -= 1
            else:
                ax += tau[rgt, 0]
                ay += tau[rgt, 1]
                cx += tau[rgt, 0] * dr
                cy += tau[rgt, 1] * dr
                rgt += 1
        u = min(u, vcap)
        g = int(sv[v] / h)
        x = u * u
        for gi in (g, g + 1):
            if 0 <= gi < n and x < xk[gi]:
                xk[gi] = x
        # samples within one step of the vertex see its own turning with weight 1 - d / L:
        # that share of the acceleration budget, v |tau| / dt (linear in v, unlike the
        # distributed curvature's v^2 kappa), is reserved in _accel_interval via kv
        if u > 0.0:
            L = u * dt
            kvu = math.sqrt(tau[v, 0] ** 2 + tau[v, 1] ** 2) / dt
            g0 = max(0, int((sv[v] - L) / h))
            g1 = min(n - 1, int((sv[v] + L) / h) + 1)
            for gi in range(g0, g1 + 1):
                w = 1.0 - abs(gi * h - sv[v]) / L
                if w > 0.0 and kvu * w > kv[gi]:
                    kv[gi] = kvu * w
            _joint_share(v, sv, tau, jac, gv, qa, L, n, h, dt, kvq)


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _followed_curvature(sv, tau, n, h, reach, kc, ctau):
    """The followed polyline's own curvature, 1/mm, at the grid points (kc[0:n], in place).

    The polyline the samples follow (arc length sv (K,) mm, turning vectors tau (K, 2))
    turns its tangent by |sum tau_w| over the points within ``reach`` / 2 mm either side
    of a point w; over that length it is the curvature a step of ``reach`` mm (one output
    step at the speed bound) sees there (thesis eq. 4.8: the radial v^2 kappa). The
    vector sum lets the smoothed curve's roughness below the grid's scale cancel. The
    tangential acceleration of a grid segment is planned at its ends (_pass: forward at
    the first, backward at the second), from the 0.4 mm grid's curvature there, which
    misses an arc shorter than the grid between them: each point's curvature goes to the
    two grid points around it (spread to every grid point within ``reach``, a smooth
    wavy path's peaks widened: 4.6 % over TOPP-RA's time at 4 ms). Used where the
    followed polyline is finer than the grid (an output step under the grid's, see
    ``motion._round_corners``). ctau (K+1, 2): work array.
    """
    for i in range(n):
        kc[i] = 0.0
    K = sv.shape[0]
    if K < 3 or reach <= 0.0:
        return
    ctau[0, 0] = 0.0
    ctau[0, 1] = 0.0
    for w in range(K):
        ctau[w + 1, 0] = ctau[w, 0] + tau[w, 0]
        ctau[w + 1, 1] = ctau[w, 1] + tau[w, 1]
    half = 0.5 * reach
    lo = 0
    hi = 0
    for w in range(1, K - 1):
        if tau[w, 0] == 0.0 and tau[w, 1] == 0.0:
            continue
        while sv[w] - sv[lo] > half:
            lo += 1
        if hi < w:
            hi = w
        while hi + 1 < K and sv[hi + 1] - sv[w] <= half:
            hi += 1
        tx = ctau[hi + 1, 0] - ctau[lo, 0]
        ty = ctau[hi + 1, 1] - ctau[lo, 1]
        c = math.sqrt(tx * tx + ty * ty) / reach
        g0 = min(max(int(sv[w] / h), 0), n - 1)
        g1 = min(g0 + 1, n - 1)
        for gi in range(g0, g1 + 1):
            if c > kc[gi]:
                kc[gi] = c


#: A vertex's share of a joint's acceleration below this fraction of the bound is not
#: reserved (:func:`_joint_share`).
JOINT_SHARE_MIN = 1e-3


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _joint_share(v, sv, tau, jac, gv, qa, L, n, h, dt, kvq):
    """Reserve in kvq (n, m) each joint's share of vertex v's own turn, |J_j tau_v| / dt
    per mm/s (jac[gv] (m, 2): the Jacobian there), weighted by 1 - d / L within one step L of
    it (as _vertex_bounds does kv). A share under ``JOINT_SHARE_MIN`` of the joint's bound
    at the step's speed L / dt is not reserved (most vertices of a smoothed path turn by
    a hair; reserved or not, no planned speed moved measurably)."""
    g0 = max(0, int((sv[v] - L) / h))
    g1 = min(n - 1, int((sv[v] + L) / h) + 1)
    for j in range(qa.shape[0]):
        if not math.isfinite(qa[j]):
            continue
        kj = abs(jac[gv, j, 0] * tau[v, 0] + jac[gv, j, 1] * tau[v, 1]) / dt
        if kj * L / dt <= JOINT_SHARE_MIN * qa[j]:
            continue
        for gi in range(g0, g1 + 1):
            w = 1.0 - abs(gi * h - sv[v]) / L
            if w > 0.0 and kj * w > kvq[gi, j]:
                kvq[gi, j] = kj * w


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _rest_segment(v1, h, a_r):
    """AREST (thesis 4.1.5, 4.2.6) for a grid segment that starts (or ends) at rest:
    s(t) = a t^2 / 2 + j t^3 / 6 from rest, reaching speed v1 after h mm.

    a_r >= 0: the requested initial acceleration; a = min(a_r, 4 v1^2 / (3 h)) and the
    jerk j follows from v1 and h. j < 0 (the acceleration falls from a) is allowed as
    long as the speed rises monotonically to v1 (a T <= 2 v1, i.e. a <= 4 v1^2 / (3 h),
    where the acceleration reaches 0 at T). a_r < 0: constant acceleration v1^2 / (2 h)
    (rest curves off). Returns (duration T, initial acceleration a, jerk j); v1 <= 0
    gives (0, 0, 0).
    """
    if v1 <= 0.0:
        return 0.0, 0.0, 0.0
    if a_r < 0.0:
        return 2.0 * h / v1, v1 * v1 / (2.0 * h), 0.0
    a = max(min(a_r, 4.0 * v1 * v1 / (3.0 * h)), 0.0)
    # the root of a T^2 / 6 + v1 T / 3 = h without cancellation: written as
    # (-v1 / 3 + sqrt(...)) / (a / 3) it gave T = 0 for a = 1e-300 (and an infinite jerk)
    T = 2.0 * h / (v1 / 3.0 + math.sqrt(v1 * v1 / 9.0 + 2.0 * a * h / 3.0))
    return T, a, 2.0 * (v1 - a * T) / (T * T)


@njit(cache=True, fastmath=_FM, error_model="numpy")
def _seg_dt(vp, i, n, h, a0, a1):
    """Duration of grid segment i -> i+1 of a piece of n points (the first and last
    segments, from and to rest, follow _rest_segment with initial accelerations a0, a1)."""
    if i == 0 and vp[0] == 0.0:
        return _rest_segment(vp[1], h, a0)[0]
    if i == n - 2 and vp[n - 1] == 0.0:
        return _rest_segment(vp[n - 2], h, a1)[0]
    vs = vp[i] + vp[i + 1]
    return 2.0 * h / vs if vs > 1e-12 else 0.0


@njit(cache=True, fastmath=_FM, error_model="numpy")
def rest_accelerations(gstart, h, v, T, dt, a_r, dmin0, dmin1, cap0, cap1):
    """AREST and the joint encoder resolution (thesis 4.2.6): initial accelerations of
    the from-rest (a0) and to-rest (a1) curves of every piece such that the first and the
    last output step move the tool by at least dmin0[p] / dmin1[p] mm (the displacement
    that turns some joint by its encoder resolution at that end).

    The first sample is at c dt on the piece's own clock (c = T / (nsamp dt) <= 1, see
    sample_pieces), so its displacement is a0 (c dt)^2 / 2 + j0 (c dt)^3 / 6 while it lies
    in the rest segment (>= h after it). Where that falls short, a0 is raised (up to
    cap0[p], the total and joint acceleration bounds at rest, and to what the rest segment
    allows, _rest_segment), which shortens the piece and so changes c: a few rounds.
    a_r: the configured initial acceleration (< 0: constant acceleration, jerk off),
    lowered to cap0[p] / cap1[p] where these are smaller (as speed_profiles planned).
    Returns a0 (P,), a1 (P,), T (P,) (durations updated).
    """
    P = gstart.shape[0] - 1
    a0 = np.full(P, a_r)
    a1 = np.full(P, a_r)
    if a_r >= 0.0:
        a0 = np.minimum(a0, cap0)
        a1 = np.minimum(a1, cap1)
    Tn = T.copy()
    for p in range(P):
        if dmin0[p] <= 0.0 and dmin1[p] <= 0.0:
            continue
        i0 = gstart[p]
        n = gstart[p + 1] - i0
        hp = h[p]
        vs = v[i0 + 1]
        ve = v[i0 + n - 2]
        if vs <= 0.0 or ve <= 0.0 or T[p] <= 0.0:
            continue
        r0 = _rest_segment(vs, hp, a0[p])
        r1 = _rest_segment(ve, hp, a1[p])
        tint = T[p] - r0[0] - r1[0]
        for _ in range(12):
            Tp = tint + r0[0] + r1[0]
            r = Tp / max(1.0, math.ceil(Tp / dt - 1e-9))  # c dt
            d0 = hp if r >= r0[0] else (0.5 * r0[1] + r0[2] * r / 6.0) * r * r
            d1 = hp if r >= r1[0] else (0.5 * r1[1] + r1[2] * r / 6.0) * r * r
            grew = False
            if d0 < dmin0[p] and r0[1] < cap0[p] * (1.0 - 1e-9):
                want = min(cap0[p], max(r0[1], 1e-9) * 1.05 * dmin0[p] / max(d0, 1e-300))
                nr = _rest_segment(vs, hp, want)
                if nr[1] > r0[1] * (1.0 + 1e-9):  # else the rest segment allows no more
                    a0[p] = want
                    r0 = nr
                    grew = True
            if d1 < dmin1[p] and r1[1] < cap1[p] * (1.0 - 1e-9):
                want = min(cap1[p], max(r1[1], 1e-9) * 1.05 * dmin1[p] / max(d1, 1e-300))
                nr = _rest_segment(ve, hp, want)
                if nr[1] > r1[1] * (1.0 + 1e-9):
                    a1[p] = want
                    r1 = nr
                    grew = True
            if not grew:
                break
        Tn[p] = tint + r0[0] + r1[0]
    return a0, a1, Tn


class PieceGrid(NamedTuple):
    """The path to time, cut into pieces sampled on a uniform grid.

    gstart (P+1,) int64: grid points of piece p are ``gstart[p]:gstart[p+1]``; h (P,) mm,
    each piece's grid step; xy (N, 2) mm, the grid points; vstart (P+1,) int64, vs_loc
    (K,) mm, vtau (K, 2): the vertices of the polyline each piece follows, their arc
    length from the piece start and turning vectors; gjac (N, m, 2): the joints' Jacobian
    at the grid points (joint units per mm; see _vertex_bounds).
    """

    gstart: np.ndarray
    h: np.ndarray
    xy: np.ndarray
    vstart: np.ndarray
    vs_loc: np.ndarray
    vtau: np.ndarray
    gjac: np.ndarray


class CartesianLimits(NamedTuple):
    """The tool point's constraint (thesis 4.1.2-4.1.5): speed vcap (P,) mm/s per piece,
    acceleration accel mm/s^2, jerk mm/s^3 (applied when jerk_on), rest_accel mm/s^2, the
    initial/final acceleration of the from/to-rest curves (thesis 4.2.6), and rest_cap0,
    rest_cap1 (P,) mm/s^2, the largest acceleration at each piece's start / end at rest
    (the joints' bounds over their rates there; rest_accel is lowered to them)."""

    vcap: np.ndarray
    accel: float
    jerk: float
    jerk_on: bool
    rest_accel: float
    rest_cap0: np.ndarray
    rest_cap1: np.ndarray


class JointLimits(NamedTuple):
    """The robot's joint constraint: q (N, m) joint values on the grid (rad or mm), and
    per-joint speed, acceleration and jerk bounds vel, acc, jerk (m,) (inf = none)."""

    q: np.ndarray
    vel: np.ndarray
    acc: np.ndarray
    jerk: np.ndarray


class Sampling(NamedTuple):
    """How the profiles are evaluated: dt s, the output time step (see _step_curvature);
    jerk_window mm, the length over which curvature is averaged before taking its slope
    for the jerk bounds; jcon_tol, the JCON iteration's relative tolerance; fine_follow,
    whether the followed polyline is finer than the grid (an output step under the
    grid's: its own curvature bounds the speed too, _followed_curvature)."""

    dt: float
    jerk_window: float
    jcon_tol: float
    fine_follow: bool


@njit(cache=True, fastmath=_FM, error_model="numpy")
def speed_profiles(grid, cart, joints, sampling):
    """VCON + ACON forward/backward + JCON for every piece (thesis 4.1.2-4.1.5).

    One object per constraint, as TOPP-RA takes them: grid (:class:`PieceGrid`), the
    tool point's limits (:class:`CartesianLimits`), the joints' (:class:`JointLimits`),
    and the evaluation (:class:`Sampling`).
    Returns v (N,) mm/s on the grid, envelope (N,) mm/s, and the piece
    durations T (P,) s.
    """
    gstart, h, xy = grid.gstart, grid.h, grid.xy
    vstart, vs_loc, vtau, gjac = grid.vstart, grid.vs_loc, grid.vtau, grid.gjac
    vcap, A, J = cart.vcap, cart.accel, cart.jerk
    jerk_on, a_rest = cart.jerk_on, cart.rest_accel
    cap0, cap1 = cart.rest_cap0, cart.rest_cap1
    q, qv, qa, qj = joints.q, joints.vel, joints.acc, joints.jerk
    dt, jerk_window, jcon_tol = sampling.dt, sampling.jerk_window, sampling.jcon_tol
    fine_follow = sampling.fine_follow
    N = xy.shape[0]
    m = q.shape[1]
    P = gstart.shape[0] - 1
    v = np.zeros(N)
    env = np.zeros(N)
    T = np.zeros(P)
    # work arrays sized for the longest piece, reused (they stay in cache)
    nmax = 0
    for p in range(P):
        nmax = max(nmax, gstart[p + 1] - gstart[p])
    p1 = np.zeros((nmax, 2))
    p2 = np.zeros((nmax, 2))
    p3 = np.zeros((nmax, 2))
    qd1 = np.zeros((nmax, m))
    qd2 = np.zeros((nmax, m))
    qd3 = np.zeros((nmax, m))
    kap = np.zeros(nmax)
    jeff = np.full(nmax, np.inf)
    fwd = np.zeros(nmax)
    c2 = np.zeros((nmax + 1, 2))
    xk = np.zeros(nmax)
    kc = np.zeros(nmax)
    kv = np.zeros(nmax)
    kvq = np.zeros((nmax, m))
    cq = np.zeros((nmax + 1, m))
    kmax = 0
    for p in range(P):
        kmax = max(kmax, vstart[p + 1] - vstart[p])
    ctau = np.zeros((kmax + 1, 2))
    for p in range(P):
        g0 = gstart[p]
        n = gstart[p + 1] - g0
        hp = h[p]
        w = int(0.5 * jerk_window / hp + 0.5)
        _derivs(xy[g0:g0 + n], 0, n, hp, w, p1, p2, p3)
        _derivs(q[g0:g0 + n], 0, n, hp, w, qd1, qd2, qd3)
        vp = v[g0:g0 + n]
        ep = env[g0:g0 + n]
        vc2 = vcap[p] * vcap[p]
        _step_curvature(n, hp, vcap[p], dt, A, qa, p2, qd2, c2, cq)
        _vertex_bounds(vs_loc[vstart[p]:vstart[p + 1]], vtau[vstart[p]:vstart[p + 1]],
                       gjac[g0:g0 + n], n, hp, vcap[p], dt, A, qa, xk, kv, kvq,
                       ctau)
        if fine_follow:
            _followed_curvature(vs_loc[vstart[p]:vstart[p + 1]],
                                vtau[vstart[p]:vstart[p + 1]], n, hp, vcap[p] * dt, kc,
                                ctau)
        for i in range(n):
            kap[i] = math.sqrt(p2[i, 0] ** 2 + p2[i, 1] ** 2)
            if fine_follow and kc[i] > kap[i]:
                kap[i] = kc[i]
            # ---- VCON: the maximum-speed envelope (thesis 4.1.2, eqs. 4.4, 4.5)
            x = min(vc2, xk[i])
            if kap[i] > _EPS:
                x = min(x, A / kap[i])
            for j in range(m):
                a1 = abs(qd1[i, j])
                if a1 > _EPS and math.isfinite(qv[j]):
                    x = min(x, (qv[j] / a1) ** 2)
                a2 = abs(qd2[i, j])
                if a2 > _EPS and math.isfinite(qa[j]):
                    x = min(x, qa[j] / a2)
            je = np.inf
            if jerk_on:
                # |p'''| v^3 <= J and |q'''_j| v^3 <= qj_j: one cube root for all of them
                j3 = math.sqrt(p3[i, 0] ** 2 + p3[i, 1] ** 2)
                rj = J / j3 if j3 > _EPS else np.inf
                je = J
                for j in range(m):
                    a3 = abs(qd3[i, j])
                    if a3 > _EPS and qj[j] < rj * a3:
                        rj = qj[j] / a3
                    a1 = abs(qd1[i, j])
                    if a1 > _EPS and qj[j] < je * a1:
                        je = qj[j] / a1
                if rj < np.inf and x * x * x > rj * rj:  # x > rj^(2/3)
                    c = np.cbrt(rj)
                    x = c * c
            jeff[i] = je
            # the acceleration interval must be non-empty at the envelope: bisect if not
            lo, hi = _accel_interval(i, x, 1.0, kap, kv, kvq, qd1, qd2, A, qa)
            if lo > hi:
                xl = 0.0
                xh = x
                for _ in range(50):
                    xm = 0.5 * (xl + xh)
                    lo, hi = _accel_interval(i, xm, 1.0, kap, kv, kvq, qd1, qd2, A, qa)
                    if lo <= hi:
                        xl = xm
                    else:
                        xh = xm
                x = xl
            ep[i] = math.sqrt(x)
        ep[0] = 0.0
        ep[n - 1] = 0.0
        # ---- ACON forward and backward, with AREST start/end conditions (4.1.3, 4.1.5)
        ar0 = min(a_rest, cap0[p])
        ar1 = min(a_rest, cap1[p])
        _pass(vp, ep, 0, n, 1, hp, kap, kv, kvq, qd1, qd2, A, qa, jeff, jerk_on, ar0, cap0[p])
        for i in range(n):
            fwd[i] = vp[i]
        _pass(vp, fwd, 0, n, -1, hp, kap, kv, kvq, qd1, qd2, A, qa, jeff, jerk_on, ar1,
              cap1[p])
        # ---- JCON (4.1.4)
        if jerk_on:
            for _ in range(3):
                if _jcon(vp, 0, n, hp, jeff, jcon_tol) == 0:
                    break
        # ---- duration (AREST: the first and last segments from and to rest)
        tt = 0.0
        for i in range(n - 1):
            tt += _seg_dt(vp, i, n, hp, ar0 if jerk_on else -1.0, ar1 if jerk_on else -1.0)
        T[p] = tt
    return v, env, T


@njit(cache=True, fastmath=_FM, error_model="numpy")
def sample_pieces(gstart, h, v, T, nsamp, sstart, dt, a0, a1):
    """Sample every piece at constant dt (thesis 4.2.6 output resolution).

    Piece p lasts T[p] s and gets nsamp[p] + 1 samples (k = 0..nsamp[p]); every speed
    is scaled by c = T[p] / (nsamp[p] dt) <= 1 so the last sample lands on the end point
    at rest (a uniform slow-down keeps every bound: speed scales by c, acceleration by
    c^2, jerk by c^3). Samples of piece p are written at
    ``sstart[p] .. sstart[p] + nsamp[p]``. Inside a grid segment the acceleration is
    constant, except in the first and last segments, which follow the AREST curves of
    _rest_segment with the initial accelerations a0[p] and a1[p] (< 0: constant
    acceleration; see rest_accelerations). Returns s (M,) mm from the piece start and speed (M,)
    mm/s.
    """
    P = gstart.shape[0] - 1
    M = sstart[P - 1] + nsamp[P - 1] + 1 if P > 0 else 0
    s_out = np.zeros(M)
    v_out = np.zeros(M)
    for p in range(P):
        i0 = gstart[p]
        i1 = gstart[p + 1]
        n = i1 - i0
        vp = v[i0:i1]
        hp = h[p]
        ns = nsamp[p]
        c = T[p] / (ns * dt) if ns > 0 else 1.0
        o = sstart[p]
        i = 0
        t_i = 0.0
        ar0 = a0[p]
        ar1 = a1[p]
        dti = _seg_dt(vp, 0, n, hp, ar0, ar1)
        for k in range(ns + 1):
            tau = k * dt * c
            if k == ns:
                s_out[o + k] = (n - 1) * hp
                v_out[o + k] = vp[n - 1] * c
                continue
            while i < n - 2 and t_i + dti <= tau:
                t_i += dti
                i += 1
                dti = _seg_dt(vp, i, n, hp, ar0, ar1)
            r = tau - t_i
            if r > dti:
                r = dti
            if i == 0 and vp[0] == 0.0:
                Tr, ar, j = _rest_segment(vp[1], hp, ar0)
                ds = 0.5 * ar * r * r + j * r * r * r / 6.0
                sp = ar * r + 0.5 * j * r * r
            elif i == n - 2 and vp[n - 1] == 0.0:
                Tr, ar, j = _rest_segment(vp[n - 2], hp, ar1)
                q = dti - r  # time left to the rest point
                ds = hp - (0.5 * ar * q * q + j * q * q * q / 6.0)
                sp = ar * q + 0.5 * j * q * q
            else:
                acc = (vp[i + 1] ** 2 - vp[i] ** 2) / (2.0 * hp)
                ds = vp[i] * r + 0.5 * acc * r * r
                sp = vp[i] + acc * r
            if ds > hp:
                ds = hp
            if ds < 0.0:
                ds = 0.0
            s_out[o + k] = i * hp + ds
            v_out[o + k] = sp * c
    return s_out, v_out


@njit(cache=True, fastmath=_FM, error_model="numpy")
def polyline_vertices(pts, start):
    """Vertices of concatenated polylines (piece k is ``pts[start[k]:start[k+1]]``): arc
    length from the piece start (K,) mm and turning vectors (K, 2) = change of the unit
    tangent, zero at the piece ends."""
    K = pts.shape[0]
    s_loc = np.zeros(K)
    tau = np.zeros((K, 2))
    for p in range(start.shape[0] - 1):
        a = start[p]
        b = start[p + 1]
        ux = 0.0
        uy = 0.0
        for i in range(a + 1, b):
            dx = pts[i, 0] - pts[i - 1, 0]
            dy = pts[i, 1] - pts[i - 1, 1]
            ln = math.sqrt(dx * dx + dy * dy)
            s_loc[i] = s_loc[i - 1] + ln
            inv = 1.0 / max(ln, 1e-300)
            nx = dx * inv
            ny = dy * inv
            if i > a + 1:
                tau[i - 1, 0] = nx - ux
                tau[i - 1, 1] = ny - uy
            ux = nx
            uy = ny
    return s_loc, tau


@njit(cache=True, fastmath=_FM, error_model="numpy")
def follow_samples(s_loc, sstart, L, fstart, fu, fxy, s0):
    """Points of the followed polylines at the sampled arc lengths: piece p's samples
    ``sstart[p]:sstart[p+1]`` at ``s_loc`` mm from its start (clipped to its length
    L[p]) on ``fxy[fstart[p]:fstart[p+1]]`` (parameter fu in S units, piece start s0[p]),
    linear between its points; the first and last sample exactly on the piece's ends.
    Returns (M, 2) mm."""
    M = s_loc.shape[0]
    xy = np.empty((M, 2))
    for p in range(sstart.shape[0] - 1):
        f0 = fstart[p]
        f1 = fstart[p + 1] - 1
        j = f0
        for k in range(sstart[p], sstart[p + 1]):
            s = min(s_loc[k], L[p]) + s0[p]
            while j < f1 - 1 and fu[j + 1] <= s:
                j += 1
            du = fu[j + 1] - fu[j]
            t = (s - fu[j]) / du if du > 0.0 else 0.0
            t = min(max(t, 0.0), 1.0)
            xy[k, 0] = fxy[j, 0] + t * (fxy[j + 1, 0] - fxy[j, 0])
            xy[k, 1] = fxy[j, 1] + t * (fxy[j + 1, 1] - fxy[j, 1])
        xy[sstart[p], 0] = fxy[f0, 0]
        xy[sstart[p], 1] = fxy[f0, 1]
        xy[sstart[p + 1] - 1, 0] = fxy[f1, 0]
        xy[sstart[p + 1] - 1, 1] = fxy[f1, 1]
    return xy


@njit(cache=True, fastmath=_FM, error_model="numpy")
def smooth_followed(gstart, gxy, gs, h, s0, PV, S, pvs, sigma_pts, tol, max_turn):
    """Path smoothing of resampled pieces (see smooth_pieces) in one call: the followed
    polyline is the grid plus the input's interior vertices that are not on a grid point,
    merged by arc length, all moved onto the smoothing curve.

    gstart (P+1,) int64, gxy (G, 2) mm and gs (G,) (S units) the raw grid, h (P,) mm,
    s0 (P,) piece starts (S units); PV (K, 2) mm, S (K,) the piece vertex lists and their
    arc length, pvs (P+1,). Returns the smoothed grid (G, 2), the followed polyline
    fxy (F, 2) mm, its parameter fu (F,) in S units and fstart (P+1,) int64.
    """
    P = gstart.shape[0] - 1
    G = gs.shape[0]
    nv = 0
    for p in range(P):
        for j in range(pvs[p] + 1, pvs[p + 1] - 1):
            off = S[j] - s0[p]
            off -= math.floor(off / h[p]) * h[p]
            if off > 1e-9 and off < h[p] - 1e-9:
                nv += 1
    F = G + nv
    fstart = np.zeros(P + 1, np.int64)
    fu = np.empty(F)
    loc = np.empty(F)
    fraw = np.empty((F, 2))
    fg = np.empty(G, np.int64)  # position of each grid point in the followed polyline
    o = 0
    for p in range(P):
        fstart[p] = o
        j = pvs[p] + 1
        jend = pvs[p + 1] - 1
        for g in range(gstart[p], gstart[p + 1]):
            while j < jend and S[j] < gs[g]:  # vertices before this grid point
                off = S[j] - s0[p]
                off -= math.floor(off / h[p]) * h[p]
                if off > 1e-9 and off < h[p] - 1e-9:
                    fu[o] = S[j]
                    loc[o] = S[j] - s0[p]
                    fraw[o, 0] = PV[j, 0]
                    fraw[o, 1] = PV[j, 1]
                    o += 1
                j += 1
            fu[o] = gs[g]
            loc[o] = gs[g] - s0[p]
            fraw[o, 0] = gxy[g, 0]
            fraw[o, 1] = gxy[g, 1]
            fg[g] = o
            o += 1
    fstart[P] = o
    fxy = smooth_pieces(gstart, gxy, h, fstart, loc, fraw, sigma_pts, tol, max_turn)
    gsm = np.empty((G, 2))
    for g in range(G):
        gsm[g, 0] = fxy[fg[g], 0]
        gsm[g, 1] = fxy[fg[g], 1]
    return gsm, fxy, fu, fstart
