"""Calibrations a real cell needs: the laser's offset and latency, the valves' tables.

Laser (thesis 5.2.1). The laser spot is ``laser_offset_mm`` from the end effector (EE) in
the robot base frame (the frames are pure translations, :func:`icefab.paths.to_base_frame`),
and a sample is tagged with the EE position the encoders report at its instant while the
surface was read ``latency`` seconds earlier. Along a straight scan at signed speed ``v``
(mm/s along the scan axis) an elevation edge at base-frame coordinate ``X`` is therefore
seen at the tagged EE coordinate::

    x_tag = X - offset + v * latency                                  (1)

* **Latency** (the thesis' "sharp elevation change mapped with parallel paths in opposite
  directions"): the edge's position is unknown, but the same edge crossed at ``+v`` and
  ``-v`` is seen ``2 v latency`` apart. :func:`fit_latency` fits every crossing of every
  scan by least squares to ``x_tag = a + b * across + v * latency`` (``across``: the other
  coordinate, so a skewed edge costs nothing) and gives the latency and its standard
  uncertainty from the residuals. This is what the thesis reads from the "skewed
  topography at the common edge between paths traversed in opposite directions", without
  building the interpolation surface.
* **Offset** (the thesis' "test jig with known elevation changes"): a jig with edges at
  known base-frame positions (:class:`JigEdge`, ``x`` edges crossed by scans along x,
  ``y`` edges by scans along y) gives, per crossing and by (1),
  ``offset = X - x_tag + v * latency``; :func:`fit_offset` averages them per axis and adds
  the latency's uncertainty times the mean speed (slow scans make it small).
* A crossing is where the reading passes the middle of the levels on either side of a
  jump (linear interpolation between the two samples around it, :func:`find_crossings`).
* The thesis' tolerances: offset known within 0.2 mm, latency within 0.002 s
  (:data:`OFFSET_TOLERANCE_MM`, :data:`LATENCY_TOLERANCE_S`); a calibration meets them
  when its expanded uncertainty (95 %: the standard uncertainty times Student's t for the
  fit's degrees of freedom, about 2 for many crossings, :func:`expanded`) is within them.

Scan files (CSV, one header line, ``#`` comments)::

    scan,t_s,x_mm,y_mm,z_mm        <- scan id, sample time, tagged EE position (base frame),
    0,0.000,200.000,-50.000,12.3      laser reading; a scan is one straight path

Jig files: ``axis,position_mm,step_mm`` (``x`` or ``y``; the edge's base-frame coordinate;
the elevation change when the coordinate increases across it).

Valves (thesis 6.1): "approximately 20 values in the frequency range to be used are
selected; for each value, the mass of liquid deposited during a certain amount of time is
found". Mass files: the header line ``frequency_hz,duration_s,mass_g`` (the columns in any
order), then one run a row (repeats allowed); with the
material's density (``materials.*.density_g_cm3``) each row is a flow
``Q = 1000 * mass / (density * duration)`` mm^3/s. :func:`fit_valve_table` fits them with
a polynomial through 0 Hz = no flow (weighted least squares on relative deviations, the
degree up to 5 chosen by AICc), and the table is the fit at the measured frequencies: it
averages the scatter of single runs over neighbouring frequencies (with ~20 frequencies
and 2 runs each, a 1 % run-to-run scatter leaves about 0.5 % in the table instead of the
0.7 % of plain per-frequency means) and must increase strictly; it is written by
:func:`write_valve_table` in the layout :func:`icefab.flow.load_calibration` reads.
Before the fit each run is held to the other runs at its frequency (more than 10 % from
their median, or two runs more than 20 % apart, is refused naming its line: a run weighed
twice, cut short or spilt), and the top frequency, which has nothing above it to hold it,
to the trend of the few below it (a valve saturates, flattening at its top; a jump above
that trend is refused where the table would be the runs' means, and a single run there
that a polynomial follows is written with a warning).

The synthetic generators (:func:`scan_line`, :func:`synthetic_jig_scans`,
:func:`synthetic_edge_scans`, :func:`synthetic_masses`) produce such data with known true
values and realistic noise (laser noise, encoder noise, a finite spot, per-path latency
jitter, random sampling phase; balance resolution and per-run flow scatter), so that the
virtual cell and the tests can check that the calibrations recover them.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from icefab.atomic import write_atomic
from icefab.errors import ConfigError, FlowError
from icefab.inputs import read_input_text

log = logging.getLogger(__name__)

#: Thesis 5.2.1: the laser's position must be known within 0.2 mm ...
OFFSET_TOLERANCE_MM = 0.2
#: ... and the latency of its measurements within 0.002 s.
LATENCY_TOLERANCE_S = 0.002
#: Confidence level of the expanded uncertainties.
CONFIDENCE = 0.95


def expanded(sigma: float, dof: int) -> float:
    """95 % expanded uncertainty of a standard uncertainty ``sigma`` estimated with ``dof``
    degrees of freedom (Student's t: 12.7 sigma for 1, 2.0 for 60)."""
    from scipy.stats import t

    return float(sigma * t.ppf(0.5 + 0.5 * CONFIDENCE, max(int(dof), 1)))

SCAN_HEADER = "scan,t_s,x_mm,y_mm,z_mm"
JIG_HEADER = "axis,position_mm,step_mm"
MASS_HEADER = "frequency_hz,duration_s,mass_g"


# =========================================================================== files


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _columns(path: Path, n: int, cells: list[str], names: list[str]) -> list[int]:
    """Which column of the file holds each expected column, from a header row ``cells``
    (line ``n``): the expected names in any order, in any case. Other names are refused,
    naming the first: read by position, 'frequency,seconds,grams' or a header in other
    units put its values in columns it never named (a docs hunt's)."""
    lowered = [c.lower() for c in cells]
    expected = f"expected the columns {','.join(names)} (in any order)"
    for c in cells:
        if c.lower() not in names:
            raise ConfigError(f"{path}:{n}: unknown column {c!r} in the header; {expected}")
    for c in lowered:
        if lowered.count(c) > 1:
            raise ConfigError(f"{path}:{n}: the header names {c!r} twice; {expected}")
    return [lowered.index(name) for name in names]


def _rows(path: Path, header: str, kinds: str, kind: str = "calibration", *,
          need_header: bool = False) -> list[tuple[int, list]]:
    """The data rows of a small CSV file: (line number, values) per row.

    ``kinds``: one letter per column, ``f`` a finite float, ``i`` an integer, ``a`` an
    axis name (x or y). A first line whose first cell is not a number is a header: the
    columns of ``header`` in any order (other names are refused); ``need_header``: a file
    without one is refused (else its columns are ``header``'s); ``#`` starts a comment; a
    UTF-8 byte-order mark is dropped. The file must be a regular file within
    ``icefab.inputs.MAX_BYTES[kind]``. Raises ConfigError naming the file and line.
    """
    text = read_input_text(path, kind, ConfigError)
    names = header.split(",")
    order: list[int] | None = None
    out: list[tuple[int, list]] = []
    seen_header = False
    for n, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        cells = [c.strip() for c in line.split(",")]
        first_is_data = (cells[0].lower() in ("x", "y") if kinds[0] == "a"
                         else _is_number(cells[0]))
        # a header names its columns: a first row with numbers in it is data, however
        # its first cell reads ("l00,60,1.4" or "z,230,2" were taken for a header and
        # dropped without a word, a tester's)
        if not out and not seen_header and not first_is_data \
                and not any(_is_number(c) for c in cells):
            seen_header = True
            if len(cells) == len(kinds):
                order = _columns(path, n, cells, names)
                continue
        if need_header and not seen_header:
            raise ConfigError(f"{path}:{n}: no header line: expected the first line "
                              f"'{header}' (its columns in any order), got {raw.strip()!r}")
        if len(cells) != len(kinds):
            raise ConfigError(f"{path}:{n}: expected {len(kinds)} columns ({header}), got "
                              f"{len(cells)}: {raw.strip()!r}")
        if order is not None:
            cells = [cells[k] for k in order]
        values: list = []
        for cell, kind_, name in zip(cells, kinds, names):
            if kind_ == "a":
                if cell.lower() not in ("x", "y"):
                    raise ConfigError(f"{path}:{n}: {name} must be 'x' or 'y', got {cell!r}")
                values.append(cell.lower())
                continue
            try:
                if "_" in cell:   # Python reads 1_00 as 100; no instrument writes it
                    raise ValueError(cell)
                v = int(cell) if kind_ == "i" else float(cell)
            except ValueError:
                raise ConfigError(f"{path}:{n}: {name} must be "
                                  f"{'an integer' if kind_ == 'i' else 'a number'}, got "
                                  f"{cell!r}") from None
            if kind_ == "f" and not math.isfinite(v):
                raise ConfigError(f"{path}:{n}: {name} must be finite, got {cell!r}")
            values.append(v)
        out.append((n, values))
    if not out:
        raise ConfigError(f"{path}: no data rows (expected lines '{header}')")
    return out


@dataclass(frozen=True, eq=False)
class Scan:
    """One straight laser scan: samples in time order.

    scan: its id; t: (n,) float64 s; xy: (n, 2) float64 mm, tagged EE positions in the
    robot base frame (encoders at each sample instant); z: (n,) float64 mm, readings.
    """

    scan: int
    t: np.ndarray
    xy: np.ndarray
    z: np.ndarray


def read_scans(path: str | os.PathLike) -> list[Scan]:
    """Scans from a CSV file (module docstring); ConfigError naming the file and line for a
    malformed row, a scan with fewer than 8 samples or time not increasing."""
    path = Path(path)
    rows = _rows(path, SCAN_HEADER, "iffff", kind="scans")
    by: dict[int, list[tuple[int, list]]] = {}
    for n, v in rows:
        by.setdefault(v[0], []).append((n, v))
    scans = []
    for sid, items in by.items():
        t = np.array([v[1] for _, v in items])
        if np.any(np.diff(t) <= 0):
            k = int(np.argmax(np.diff(t) <= 0)) + 1
            raise ConfigError(f"{path}:{items[k][0]}: scan {sid}: t_s must increase within a "
                              f"scan ({t[k - 1]:g} then {t[k]:g})")
        if len(items) < 8:
            raise ConfigError(f"{path}:{items[0][0]}: scan {sid} has {len(items)} samples; "
                              "expected at least 8")
        scans.append(Scan(scan=sid, t=t, xy=np.array([[v[2], v[3]] for _, v in items]),
                          z=np.array([v[4] for _, v in items])))
    return scans


def write_scans(scans: Sequence[Scan], path: str | os.PathLike) -> None:
    """Write scans as CSV (atomically)."""
    lines = [SCAN_HEADER]
    for s in scans:
        for t, (x, y), z in zip(s.t, s.xy, s.z):
            lines.append(f"{s.scan},{t:.6f},{x:.5f},{y:.5f},{z:.5f}")
    write_atomic(path, "\n".join(lines) + "\n")


@dataclass(frozen=True)
class JigEdge:
    """An elevation edge of the test jig: at ``position_mm`` on ``axis`` (base frame; an
    ``x`` edge is the line x = position, crossed by scans along x); ``step_mm``: the
    elevation change when the coordinate increases across it."""

    axis: str
    position_mm: float
    step_mm: float


def read_jig(path: str | os.PathLike) -> list[JigEdge]:
    """Jig edges from a CSV file ``axis,position_mm,step_mm``; ConfigError naming the file
    and line for a bad row or a zero step."""
    path = Path(path)
    edges = []
    for n, (axis, pos, step) in _rows(path, JIG_HEADER, "aff"):
        if step == 0:
            raise ConfigError(f"{path}:{n}: step_mm must not be 0")
        edges.append(JigEdge(axis, pos, step))
    return edges


def write_jig(edges: Sequence[JigEdge], path: str | os.PathLike) -> None:
    write_atomic(path, "\n".join([JIG_HEADER] + [f"{e.axis},{e.position_mm:.4f},{e.step_mm:.4f}"
                                                 for e in edges]) + "\n")


# =========================================================================== crossings


@dataclass(frozen=True)
class Crossing:
    """Where a scan crossed an elevation edge.

    scan: scan id; axis: the scan axis ('x' or 'y'); tagged_mm: tagged EE coordinate along
    the axis at the crossing; across_mm: the other coordinate there; speed_mm_s: signed
    EE speed along the axis; step_mm: the elevation change in the direction of increasing
    coordinate (so the same edge has the same sign in both scan directions).
    """

    scan: int
    axis: str
    tagged_mm: float
    across_mm: float
    speed_mm_s: float
    step_mm: float


def find_crossings(scan: Scan, threshold_mm: float, *, window: int = 3,
                   levels: int = 5) -> list[Crossing]:
    """Every elevation edge a scan crosses: a change of more than ``threshold_mm`` within
    ``window`` samples. The crossing is where the reading passes the middle of the levels
    before and after the jump (medians of ``levels`` samples), interpolated linearly
    between the two samples around it; the speed is the slope of a straight line through
    the tagged coordinate against time over the samples around it. Scans that do not move
    along one axis by more than 1 mm give none."""
    t, xy, z = scan.t, scan.xy, scan.z
    travel = np.abs(xy[-1] - xy[0])
    if travel.max() < 1.0:
        return []
    ax = int(np.argmax(travel))
    s = xy[:, ax]
    n = len(z)
    w = max(1, int(window))
    if n <= 2 * w + 2 * levels:
        return []
    jump = np.abs(z[w:] - z[:-w]) > threshold_mm        # jump[i]: between i and i + w
    out: list[Crossing] = []
    i = 0
    while i < len(jump):
        if not jump[i]:
            i += 1
            continue
        j = i
        while j + 1 < len(jump) and jump[j + 1]:
            j += 1
        lo, hi = i, j + w                                # the jump lies within [lo, hi]
        i = j + 1
        if lo - levels < 0 or hi + levels >= n:
            continue                                     # too near the scan's ends
        before = float(np.median(z[lo - levels + 1:lo + 1]))
        after = float(np.median(z[hi:hi + levels]))
        if abs(after - before) <= threshold_mm:
            continue
        mid = 0.5 * (before + after)
        seg = z[lo:hi + 1] - mid
        k = np.nonzero(np.sign(seg[:-1]) != np.sign(seg[1:]))[0]
        if len(k) == 0:
            continue
        k0 = lo + int(k[0])
        f = (mid - z[k0]) / (z[k0 + 1] - z[k0])
        pos = s[k0] + f * (s[k0 + 1] - s[k0])
        tc = t[k0] + f * (t[k0 + 1] - t[k0])
        a, b = max(0, k0 - 6), min(n, k0 + 8)
        v = float(np.polyfit(t[a:b] - tc, s[a:b], 1)[0])
        if abs(v) < 1e-6:
            continue
        step = (after - before) * (1.0 if v > 0 else -1.0)
        out.append(Crossing(scan=scan.scan, axis="xy"[ax], tagged_mm=float(pos),
                            across_mm=float(xy[k0, 1 - ax]), speed_mm_s=v,
                            step_mm=float(step)))
    return out


# =========================================================================== laser fits


@dataclass(frozen=True)
class LatencyFit:
    """Latency from opposite-direction scans of one edge (thesis 5.2.1).

    latency_s and its standard uncertainty sigma_s; crossings used; residual_mm: RMS of the
    fit's residuals; speed_mm_s: mean absolute scan speed; dof: degrees of freedom of
    sigma_s.
    """

    latency_s: float
    sigma_s: float
    crossings: int
    residual_mm: float
    speed_mm_s: float
    dof: int = 1
    #: the fit's own value when it came out below 0 within its uncertainty and
    #: ``latency_s`` was set to 0 (None otherwise)
    estimate_s: float | None = None

    @property
    def expanded_s(self) -> float:
        return expanded(self.sigma_s, self.dof)


#: Half the readings' 5-95 % spread must exceed this many times their noise to hold an
#: edge: noise alone spreads 3.3 of its standard deviations, so gives a half of 1.6.
EDGE_OVER_NOISE = 3.0


def edge_threshold(scans: Sequence[Scan]) -> float:
    """Half the spread of all readings between their 5th and 95th percentiles, mm (the
    percentiles leave drop-outs and spikes of up to 5 % of the samples out). ConfigError
    when it is within :data:`EDGE_OVER_NOISE` times the readings' noise (from their first
    differences' median absolute deviation): no scan crosses an edge. Scans that never
    reached the edge gave 18 noise "crossings" and "0 +- 56 ms" (a tester's). An edge
    whose high side holds under 5 % of the samples is missed: scan across its middle.
    (Per-scan ranges of median-filtered readings, tried instead, failed on drop-outs of
    three samples and on scans of which half missed the edge.)"""
    z = [np.asarray(sc.z, dtype=np.float64) for sc in scans]
    z = [v[np.isfinite(v)] for v in z]
    zall = np.concatenate(z) if z else np.zeros(0)
    if len(zall) < 6:
        raise ConfigError("latency calibration: fewer than 6 readings")
    half = 0.5 * float(np.percentile(zall, 95) - np.percentile(zall, 5))
    d = np.concatenate([np.diff(v) for v in z if len(v) > 1])
    sigma = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / math.sqrt(2.0)
    if not half > EDGE_OVER_NOISE * sigma:
        raise ConfigError(f"latency calibration: no scan crosses an edge: half the readings' "
                          f"5-95 % spread is {half:.3g} mm, not more than {EDGE_OVER_NOISE:g} "
                          f"times their noise ({sigma:.3g} mm)")
    return half


def fit_latency(scans: Sequence[Scan], threshold_mm: float | None = None) -> LatencyFit:
    """Latency from scans across straight edges in both directions (module docstring).

    threshold_mm: smallest elevation change taken for an edge (default:
    :func:`edge_threshold`). A rising and a falling edge (a block) each get their own
    position in the fit (a block's two edges fitted as one gave 2.6 +- 17 ms, a
    tester's). Raises ConfigError when the scans do not cross an edge in both directions
    at least twice each.
    """
    if not scans:
        raise ConfigError("latency calibration: no scans")
    if threshold_mm is None:
        threshold_mm = edge_threshold(scans)
    cr = [c for s in scans for c in find_crossings(s, threshold_mm)]
    if not cr:
        raise ConfigError("latency calibration: no scan crosses an edge (an elevation change "
                          f"of more than {threshold_mm:.3g} mm)")
    axis = max("xy", key=lambda a: sum(c.axis == a for c in cr))
    cr = [c for c in cr if c.axis == axis]
    v = np.array([c.speed_mm_s for c in cr])
    if np.count_nonzero(v > 0) < 2 or np.count_nonzero(v < 0) < 2:
        raise ConfigError(f"latency calibration: {np.count_nonzero(v > 0)} crossings in the "
                          f"+{axis} and {np.count_nonzero(v < 0)} in the -{axis} direction; "
                          "need at least 2 in each (parallel paths in opposite directions)")
    across = np.array([c.across_mm for c in cr])
    x = np.array([c.tagged_mm for c in cr])
    rising = np.array([c.step_mm > 0 for c in cr])
    # x_tag = a_edge + b * across + v * latency (eq. 1 with straight, possibly skewed
    # edges; a rising and a falling one each have their own position a_edge)
    cols = [rising.astype(np.float64), (~rising).astype(np.float64)]
    cols = [c for c in cols if c.any()]
    if np.ptp(across) >= 1e-6:
        cols.append(across - across.mean())
    A = np.column_stack([*cols, v])
    coef, *_ = np.linalg.lstsq(A, x, rcond=None)
    res = x - A @ coef
    dof = max(1, len(x) - A.shape[1])
    s2 = float(res @ res) / dof
    cov = s2 * np.linalg.inv(A.T @ A)
    return LatencyFit(latency_s=float(coef[-1]), sigma_s=float(math.sqrt(cov[-1, -1])),
                      crossings=len(cr), residual_mm=float(math.sqrt(s2)),
                      speed_mm_s=float(np.mean(np.abs(v))), dof=dof)


@dataclass(frozen=True)
class OffsetFit:
    """Laser offset from jig scans (thesis 5.2.1).

    offset_mm: (x, y) laser frame origin in the EE frame; sigma_mm: (x, y) standard
    uncertainties (the crossings' scatter and the latency's uncertainty); crossings:
    (x, y) matched crossings; unmatched: crossings not within ``match_mm`` of any edge;
    expanded_mm: (x, y) 95 % expanded uncertainties (the scatter's with its n - 1 degrees
    of freedom, the latency's with the latency fit's).
    """

    offset_mm: tuple[float, float]
    sigma_mm: tuple[float, float]
    crossings: tuple[int, int]
    unmatched: int
    expanded_mm: tuple[float, float] = (0.0, 0.0)


#: A crossing's step matches a jig edge's when within this factor of it (and of its sign).
STEP_MATCH_FACTOR = 2.0


def _same_step(c: Crossing, e: JigEdge) -> bool:
    """Whether crossing ``c`` can be jig edge ``e``: the same sign, and a step within
    :data:`STEP_MATCH_FACTOR` of it. A drop-out (-99.999 over a shiny patch) makes two
    'crossings' of ~100 mm; one of them was matched to a 2 mm edge on every pass, and
    the offset came out 0.9 mm wrong, "within tolerances" (a tester's)."""
    r = c.step_mm / e.step_mm
    return 1.0 / STEP_MATCH_FACTOR <= r <= STEP_MATCH_FACTOR


#: Crossings whose offsets agree within this, mm, support the same offset (the crossings
#: scatter by micrometres; the jig's same-sign edges are millimetres apart).
OFFSET_SUPPORT_MM = 0.5


def _supported_offset(cands: np.ndarray, who: np.ndarray, nominal: float) -> float:
    """The offset that the most crossings support: the candidate offsets (each crossing
    against each jig edge it could be) with the most distinct crossings within
    :data:`OFFSET_SUPPORT_MM`, the one nearest ``nominal`` among equals; their median.

    Matching each crossing to the edge its nominal offset puts nearest locked onto the
    neighbouring edges when the nominal was 8 mm off (the jig's edges 10 mm apart): a
    tester's calibration came out 10.000 mm wrong, "within the thesis' tolerances", with
    half the crossings unmatched. At the true offset every crossing finds its edge; a
    shift by the edges' spacing leaves those at the jig's ends without one.
    """
    order = np.argsort(cands, kind="stable")
    c, w = cands[order], who[order]
    lo = np.searchsorted(c, c - OFFSET_SUPPORT_MM, side="left")
    hi = np.searchsorted(c, c + OFFSET_SUPPORT_MM, side="right")
    support = np.array([len(np.unique(w[a:b])) for a, b in zip(lo, hi)])
    best = np.flatnonzero(support == support.max())
    k = best[np.argmin(np.abs(c[best] - nominal))]
    return float(np.median(c[lo[k]:hi[k]]))


def fit_offset(scans: Sequence[Scan], jig: Sequence[JigEdge], *, latency_s: float,
               latency_sigma_s: float = 0.0, latency_dof: int = 1000,
               nominal_offset_mm: Sequence[float] = (0.0, 0.0), match_mm: float = 5.0
               ) -> OffsetFit:
    """Laser offset from scans over a jig with known edges (module docstring, eq. 1).

    On each axis the offset the most crossings support is found first
    (:func:`_supported_offset`; the nominal offset only breaks ties), then each crossing
    is matched to the jig edge on its axis with the same step sign whose expected tagged
    position ``X - offset + v * latency`` is nearest, within ``match_mm``. The estimate
    is the mean of the scans' means, its uncertainty their scatter with (scans - 1)
    degrees of freedom: the crossings of one scan share its latency jitter and sampling
    phase (their errors correlated at 0.64), and counting them as independent gave 95 %
    intervals that held the true offset 70 % of the time (a tester's coverage study;
    per scan, 93 %). With one scan on an axis, its crossings' scatter is used. Needs at
    least two matched crossings on each axis (ConfigError otherwise, naming the axis).
    """
    if not jig:
        raise ConfigError("offset calibration: the jig has no edges")
    steps = min(abs(e.step_mm) for e in jig)
    cr = [c for s in scans for c in find_crossings(s, 0.5 * steps)]
    nominal = np.asarray(nominal_offset_mm, dtype=np.float64).copy()
    for ai, a in enumerate("xy"):
        cands = [(e.position_mm - c.tagged_mm + c.speed_mm_s * latency_s, k)
                 for k, c in enumerate(cr) if c.axis == a
                 for e in jig if e.axis == a and _same_step(c, e)]
        if cands:
            arr = np.array(cands)
            nominal[ai] = _supported_offset(arr[:, 0], arr[:, 1], float(nominal[ai]))
    est: dict[str, list[float]] = {"x": [], "y": []}
    speeds: dict[str, list[float]] = {"x": [], "y": []}
    scan_of: dict[str, list[int]] = {"x": [], "y": []}
    unmatched = 0
    for c in cr:
        ai = "xy".index(c.axis)
        best, dist = None, match_mm
        for e in jig:
            if e.axis != c.axis or not _same_step(c, e):
                continue
            expect = e.position_mm - nominal[ai] + c.speed_mm_s * latency_s
            if abs(expect - c.tagged_mm) <= dist:
                best, dist = e, abs(expect - c.tagged_mm)
        if best is None:
            unmatched += 1
            continue
        est[c.axis].append(best.position_mm - c.tagged_mm + c.speed_mm_s * latency_s)
        speeds[c.axis].append(c.speed_mm_s)
        scan_of[c.axis].append(c.scan)
    off, sig, count, exp = [], [], [], []
    for a in "xy":
        e = np.asarray(est[a])
        if len(e) < 2:
            raise ConfigError(f"offset calibration: {len(e)} jig crossings along {a} matched "
                              f"an edge (a step of its size and sign, within {match_mm:g} mm "
                              "of where the offset most crossings support puts it); need at "
                              "least 2")
        v_mean = float(np.mean(speeds[a]))
        ids = np.asarray(scan_of[a])
        groups = np.unique(ids)
        if len(groups) >= 2:
            means = np.array([e[ids == g].mean() for g in groups])
            centre = float(means.mean())
            spread = float(np.std(means, ddof=1)) / math.sqrt(len(means))
            dof = len(means) - 1
        else:
            centre = float(e.mean())
            spread = float(np.std(e, ddof=1)) / math.sqrt(len(e))
            dof = len(e) - 1
        off.append(centre)
        sig.append(math.hypot(spread, abs(v_mean) * latency_sigma_s))
        exp.append(math.hypot(expanded(spread, dof),
                              abs(v_mean) * expanded(latency_sigma_s, latency_dof)))
        count.append(len(e))
    if unmatched:
        log.warning("offset calibration: %d of %d jig crossings matched no jig edge",
                    unmatched, len(cr))
    return OffsetFit(offset_mm=(off[0], off[1]), sigma_mm=(sig[0], sig[1]),
                     crossings=(count[0], count[1]), unmatched=unmatched,
                     expanded_mm=(exp[0], exp[1]))


@dataclass(frozen=True)
class LaserCalibration:
    """The laser's offset and latency with their standard uncertainties (thesis 5.2.1)."""

    offset: OffsetFit
    latency: LatencyFit

    @property
    def offset_within(self) -> bool:
        return max(self.offset.expanded_mm) <= OFFSET_TOLERANCE_MM

    @property
    def latency_within(self) -> bool:
        return self.latency.expanded_s <= LATENCY_TOLERANCE_S

    @property
    def within_tolerances(self) -> bool:
        return self.offset_within and self.latency_within

    def findings(self) -> list[str]:
        """One line per tolerance of thesis 5.2.1 that the expanded uncertainty misses."""
        out = []
        if not self.offset_within:
            out.append(f"laser offset uncertainty +-{max(self.offset.expanded_mm):.3f}"
                       f" mm (95 %) exceeds the thesis' {OFFSET_TOLERANCE_MM} mm (5.2.1): "
                       "scan the jig more often or more slowly")
        if not self.latency_within:
            out.append(f"laser latency uncertainty +-{self.latency.expanded_s:.4f} s "
                       f"(95 %) exceeds the thesis' {LATENCY_TOLERANCE_S} s (5.2.1): scan "
                       "the edge with more parallel paths or faster")
        return out

    def as_dict(self) -> dict:
        o, lt = self.offset, self.latency
        return {"laser_offset_mm": list(o.offset_mm), "laser_offset_sigma_mm": list(o.sigma_mm),
                "laser_latency_s": lt.latency_s, "laser_latency_sigma_s": lt.sigma_s,
                "offset_crossings": list(o.crossings), "latency_crossings": lt.crossings,
                "latency_residual_mm": lt.residual_mm, "unmatched_crossings": o.unmatched,
                "laser_offset_expanded_mm": list(o.expanded_mm),
                "laser_latency_expanded_s": lt.expanded_s,
                "confidence": CONFIDENCE, "offset_tolerance_mm": OFFSET_TOLERANCE_MM,
                "latency_tolerance_s": LATENCY_TOLERANCE_S,
                "within_tolerances": self.within_tolerances}

    def to_toml(self) -> str:
        """A job fragment (``[cell]`` settings) with the uncertainties as comments."""
        o, lt = self.offset, self.latency
        return (
            "# Laser calibration (icefab calibrate laser; thesis 5.2.1).\n"
            f"# offset: +-{o.sigma_mm[0]:.4f}, +-{o.sigma_mm[1]:.4f} mm (1 sigma) from "
            f"{o.crossings[0]} + {o.crossings[1]} jig crossings\n"
            f"# latency: +-{lt.sigma_s:.5f} s (1 sigma) from {lt.crossings} edge crossings "
            f"at {lt.speed_mm_s:.0f} mm/s\n"
            f"# 95 %: +-{max(o.expanded_mm):.4f} mm, +-{lt.expanded_s:.5f} s; thesis "
            f"tolerances: offset {OFFSET_TOLERANCE_MM} mm, latency "
            f"{LATENCY_TOLERANCE_S} s: {'met' if self.within_tolerances else 'NOT met'}\n"
            + (f"# latency: the fit gave {lt.estimate_s:.6f} s, below 0 within its "
               "uncertainty: written as 0\n" if lt.estimate_s is not None else "")
            + "[cell]\n"
            f"laser_offset_mm = [{o.offset_mm[0]:.4f}, {o.offset_mm[1]:.4f}]\n"
            f"laser_latency_s = {lt.latency_s:.6f}\n")


#: A negative latency is refused beyond this many times its 95 % uncertainty (about 4
#: standard deviations): at one, a laser without latency was refused in 4 of 200
#: correct calibrations (1.04-1.45 times), blamed on its time stamps (a tester's); swapped
#: time stamps read tens of times it.
NEGATIVE_LATENCY_REFUSED = 2.0


def calibrate_laser(jig_scans: Sequence[Scan], jig: Sequence[JigEdge],
                    edge_scans: Sequence[Scan], *,
                    nominal_offset_mm: Sequence[float] = (0.0, 0.0),
                    match_mm: float = 5.0) -> LaserCalibration:
    """Latency from the edge scans (:func:`fit_latency`), then the offset from the jig
    scans with that latency (:func:`fit_offset`)."""
    _check_scan_speed(edge_scans, "edge scans")
    _check_scan_speed(jig_scans, "jig scans")
    lat = fit_latency(edge_scans)
    if lat.latency_s < 0.0:
        if -lat.latency_s > NEGATIVE_LATENCY_REFUSED * lat.expanded_s:
            # a sensor cannot read before it is triggered: the laser's and the encoders'
            # time stamps are swapped or offset
            raise ConfigError(
                f"latency calibration: the laser reads {-1000 * lat.latency_s:.2f} ms "
                f"before the positions it is tagged with, more than "
                f"{NEGATIVE_LATENCY_REFUSED:g} times its 95 % uncertainty "
                f"(+-{1000 * lat.expanded_s:.2f} ms): a latency cannot be negative; check "
                "that the scans' t_s and positions are the same instants")
        # within its uncertainty of none (a tester's laser without latency read -0.03 ms,
        # and the job refused the laser.toml written with it)
        lat = dataclasses.replace(lat, latency_s=0.0, estimate_s=lat.latency_s)
    off = fit_offset(jig_scans, jig, latency_s=lat.latency_s, latency_sigma_s=lat.sigma_s,
                     latency_dof=lat.dof, nominal_offset_mm=nominal_offset_mm, match_mm=match_mm)
    return LaserCalibration(offset=off, latency=lat)


#: The scanning speeds a calibration takes, mm/s: a robot scanning a jig moves at a few to
#: a few hundred mm/s (thesis 5.2.1: 50 mm/s); far outside, the time stamps are not seconds.
SCAN_SPEED_RANGE_MM_S = (0.5, 5000.0)


def _check_scan_speed(scans: Sequence[Scan], what: str) -> None:
    """ConfigError when the scans' median speed is outside :data:`SCAN_SPEED_RANGE_MM_S`
    (a tester's edge scans timed in ms read as a 5.6 s latency, or as 'no jig crossing
    matched an edge')."""
    speeds = [float(np.hypot(*(s.xy[-1] - s.xy[0]))) / float(s.t[-1] - s.t[0])
              for s in scans if len(s.t) > 1 and s.t[-1] > s.t[0]]
    if not speeds:
        return
    v = float(np.median(speeds))
    lo, hi = SCAN_SPEED_RANGE_MM_S
    if not lo <= v <= hi:
        raise ConfigError(f"laser calibration: the {what} move at {v:.3g} mm/s (median), "
                          f"outside the {lo:g}-{hi:g} mm/s a robot scans at: t_s must be in "
                          "seconds and positions in mm (times in ms or positions in metres "
                          "make scans 1000 times slower)")


# =========================================================================== valves


@dataclass(frozen=True, eq=False)
class ValveFit:
    """A valve's frequency-flow table from mass measurements (thesis 6.1).

    frequency_hz, flow_mm3_s: (k,) the table (0 Hz = 0 first), strictly increasing.
    measured_hz, measured_mm3_s: (n,) every measurement as a flow; residual: (n,) its
    relative deviation from the fit, (measured - fit) / fit (0 for runs at 0 Hz).
    density_g_cm3: the density used.
    """

    frequency_hz: np.ndarray
    flow_mm3_s: np.ndarray
    measured_hz: np.ndarray
    measured_mm3_s: np.ndarray
    residual: np.ndarray
    density_g_cm3: float
    fit: Callable[[np.ndarray], np.ndarray] = field(repr=False, default=None)  # type: ignore
    #: "polynomial" (the fit at the measured frequencies) or "monotone means"
    method: str = "polynomial"
    #: what the table was written with but could not be checked (a single run at the top
    #: frequency above the trend below it, :func:`fit_valve_table`), one line each
    warnings: tuple[str, ...] = ()

    @property
    def rms_residual(self) -> float:
        return float(np.sqrt(np.mean(self.residual ** 2))) if len(self.residual) else 0.0


#: The highest frequency a mass run may have: ``flow.max_frequency_hz``'s upper bound.
MAX_VALVE_HZ = 1e5
#: A mass run's duration, s: long enough for the balance to read it (thesis 6.1 collects
#: for minutes), at most an hour: 60 s runs written in ms (60000, 17 h) made a table a
#: thousand times too small, with exit 0 (a tester's).
MIN_RUN_S, MAX_RUN_S = 0.1, 3600.0
#: The most flow a deposition valve's table may give, mm^3/s (10 cm^3/s: the thesis'
#: valves give under 0.3 cm^3/s, Fig. 6-1); more is masses in mg or durations in ms.
MAX_VALVE_FLOW_MM3_S = 1e4


def read_masses(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(frequency_hz, duration_s, mass_g) arrays from a mass-measurement CSV with the header
    line ``frequency_hz,duration_s,mass_g`` (its columns in any order); ConfigError naming
    the file and line for a missing header or one with other names, a bad row, a
    frequency outside 0-``MAX_VALVE_HZ``, a duration outside ``MIN_RUN_S``-``MAX_RUN_S`` or
    a mass < 0."""
    return read_mass_runs(path)[:3]


def read_mass_runs(path: str | os.PathLike
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`read_masses` and (n,) int64 the file's line of each run, so that
    :func:`fit_valve_table` can name the line of a run it refuses."""
    path = Path(path)
    rows = _rows(path, MASS_HEADER, "fff", need_header=True)
    for n, (f, d, m) in rows:
        # a row at 1e12 Hz was written into the table, and 'icefab valves' then made
        # pulses for it for minutes (a hunt's): no cell makes more than the job allows
        if not 0 <= f <= MAX_VALVE_HZ:
            raise ConfigError(f"{path}:{n}: frequency_hz must be within 0-{MAX_VALVE_HZ:g} "
                              f"Hz (the highest flow.max_frequency_hz), got {f:g}")
        if not MIN_RUN_S <= d <= MAX_RUN_S:
            raise ConfigError(f"{path}:{n}: duration_s must be within {MIN_RUN_S:g}-"
                              f"{MAX_RUN_S:g} s (a run collects for seconds to minutes; "
                              f"durations in ms?), got {d:g}")
        if m < -BALANCE_DRIFT_G:
            raise ConfigError(f"{path}:{n}: mass_g must be >= 0 (down to "
                              f"-{BALANCE_DRIFT_G:g} g, a balance's drift, counts as 0), "
                              f"got {m:g}")
    a = np.array([v for _, v in rows], dtype=np.float64)
    lines = np.array([n for n, _ in rows], dtype=np.int64)
    return a[:, 0], a[:, 1], np.maximum(a[:, 2], 0.0), lines


MAX_DEGREE = 5
#: A frequency whose mean flow is further than this (relative) from the fit is refused.
MAX_MISFIT = 0.10
#: Monotone means: a row whose flow rises less than this (relative) over the row before is
#: left out (the table is then within it of the means): the plateau of a saturated valve,
#: whose means wander by the runs' scatter (1 % a run, thesis 6.1's balance), is one row.
PLATEAU_RISE = 0.02


def _flow_polynomial(f: np.ndarray, q: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """Q(f) = sum_k c_k (f / f_max)^k, k = 1..d (no flow at 0 Hz), by least squares on the
    relative deviations (every run counts by its relative scatter), the degree d <= 5
    (and below the number of distinct frequencies) chosen by the small-sample Akaike
    criterion (AICc), so a table shaped like thesis Fig. 6-1 is followed without
    chasing the noise of single runs."""
    fmax = float(f.max())
    w = 1.0 / np.maximum(np.abs(q), 1e-9 * max(float(np.abs(q).max()), 1e-300))
    n = len(f)
    best = None
    for d in range(1, min(MAX_DEGREE, len(np.unique(f[f > 0])) - 1) + 1):
        if n - d - 1 <= 0:
            break
        A = np.column_stack([(f / fmax) ** k for k in range(1, d + 1)])
        coef, *_ = np.linalg.lstsq(A * w[:, None], q * w, rcond=None)
        rss = float(np.sum(((A @ coef - q) * w) ** 2))
        aicc = n * math.log(max(rss, 1e-300) / n) + 2 * d + 2 * d * (d + 1) / (n - d - 1)
        if best is None or aicc < best[0]:
            best = (aicc, coef)
    assert best is not None  # len(freqs) >= 3 and n >= 3 give d = 1 at least
    coef = best[1]

    def flow(x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64) / fmax
        return sum(c * x ** k for k, c in enumerate(coef, start=1)) + 0.0 * x

    return flow


#: The flow of a dead band's last row, relative to the next row's (:func:`_monotone_means`).
DEAD_BAND_FLOW = 1e-6
#: Flows below this fraction of the largest mean flow count as none when runs are held to
#: the table (:func:`fit_valve_table`'s misfit and residuals).
NO_FLOW = 1e-3


def _monotone_means(freqs: np.ndarray, means: np.ndarray, counts: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The per-frequency mean flows made to rise with the frequency (isotonic regression,
    each frequency weighted by its runs), as a table that rises strictly: of a run of
    frequencies that share one flow (a saturated valve's plateau, a dead band at 0) only
    the lowest is kept, since the valve gives no more flow above it. Returns the table's
    frequencies and flows, 0 Hz = 0 first."""
    from scipy.optimize import isotonic_regression

    y = isotonic_regression(means, weights=counts.astype(np.float64), increasing=True).x
    x = np.concatenate([[0.0], freqs])
    y = np.concatenate([[0.0], np.maximum(y, 0.0)])
    # a dead band (no flow up to some frequency): its highest frequency is the table's
    # second row, at a flow too small to give (DEAD_BAND_FLOW of the next one), so the
    # table rises strictly and passes nothing below it; keeping 0 Hz alone drew the table
    # straight across the band and refused its runs as "not rising" (a hunt's)
    dead = int(np.searchsorted(y > 0, True)) - 1   # the last row with no flow
    if 0 < dead < len(y) - 1:
        x = np.concatenate([[0.0], x[dead:]])
        y = np.concatenate([[0.0], [DEAD_BAND_FLOW * y[dead + 1]], y[dead + 1:]])
    keep = [0]
    for k in range(1, len(y)):
        # a row within PLATEAU_RISE of the last one kept is the plateau's noise (a
        # saturated valve's means wander by the runs' scatter above its saturation)
        if y[k] > y[keep[-1]] * (1.0 + PLATEAU_RISE):
            keep.append(k)
    return x[keep], y[keep]


#: A run further than this (relative) from the median flow of its frequency's runs is
#: refused when its frequency has 2 or more runs (two runs: more than twice this apart).
#: The runs of one frequency scatter by about 1 % (temperature, drops left on the nozzle,
#: the balance: :func:`synthetic_masses`' defaults), so 10 % is some 7 of their standard
#: deviations from the median of three: not scatter but a run weighed twice, cut short
#: or spilt. It is ``MAX_MISFIT``, the most a frequency's mean may be off the table: such
#: a run moves its frequency's mean by a third of it (one of three runs) and the table
#: with it, and the monotone means follow it unseen (a review's: one of three runs at
#: 1000 Hz weighed double gave a table 33 % high at 1000 Hz, with exit 0).
REPLICATE_SPREAD = MAX_MISFIT
#: ... give or take this mass, g (5 times the 1 mg a lab balance reads to): the runs of a
#: valve that barely opens collect milligrams, and their scatter is the balance's.
REPLICATE_BALANCE_G = 0.005
#: The top frequency's mean flow is held to the straight line through the mean flows of
#: the (up to) this many frequencies below it (:func:`_top_trend`): the top has no
#: frequency above it, so the rising table of monotone means can follow any value there.
TREND_POINTS = 3


def _replicate_outlier(inverse: np.ndarray, q: np.ndarray, allowance: np.ndarray,
                       floor: float) -> tuple[int, float] | None:
    """The run furthest (relative) from the median flow of its frequency's runs, as (its
    index, that median mm^3/s), when it is further than ``REPLICATE_SPREAD`` of the median
    (at least ``floor`` mm^3/s, so a dead band's near-zero runs are not compared by their
    ratio) plus its ``allowance`` (n,) mm^3/s (the balance); None when no run is.

    inverse: (n,) the frequency of each run (an index); q: (n,) the runs' flows, mm^3/s. A
    median is robust to one bad run of three or more; a frequency with a single run is
    not screened (nothing to hold it to: :func:`fit_valve_table` checks its mean).
    """
    counts = np.bincount(inverse)
    med = np.array([np.median(q[inverse == k]) for k in range(len(counts))])[inverse]
    ref = np.maximum(med, floor)
    far = (np.abs(q - med) > REPLICATE_SPREAD * ref + allowance) & (counts[inverse] >= 2)
    if not far.any():
        return None
    i = int(np.argmax(np.where(far, np.abs(q - med) / ref, -1.0)))
    return i, float(med[i])


def _top_trend(freqs: np.ndarray, means: np.ndarray, floor: float) -> float | None:
    """The flow at the top frequency, mm^3/s, on the least-squares line through the mean
    flows of the ``TREND_POINTS`` frequencies below it (freqs, means: (k,) increasing
    frequencies, Hz, and their mean flows, mm^3/s). None when fewer than 2 of those flow
    (more than ``floor``: a dead band's top has no trend to be held to) or the line gives
    no flow at the top.

    A valve's flow grows less than in proportion to its frequency (thesis Fig. 6-1) and
    flattens where it saturates, so its top lies on or below this line: on the built-in
    table (20 frequencies) 1.6 % above it, from the curvature the line leaves out.
    """
    x, y = freqs[-1 - TREND_POINTS:-1], means[-1 - TREND_POINTS:-1]
    x, y = x[y > floor], y[y > floor]
    if len(x) < 2:
        return None
    slope, intercept = np.polyfit(x, y, 1)
    at = float(slope * freqs[-1] + intercept)
    return at if at > floor else None


def _at(source: str, lines: np.ndarray | None, i: int) -> str:
    """Where run ``i`` is: ``source:line`` when the file's lines are known, else
    ``source`` and its number among the runs (from 1)."""
    return f"{source}:{int(lines[i])}" if lines is not None else f"{source}: run {i + 1}"


def fit_valve_table(frequency_hz: np.ndarray, duration_s: np.ndarray, mass_g: np.ndarray,
                    density_g_cm3: float, *, source: str = "mass measurements",
                    lines: Sequence[int] | np.ndarray | None = None) -> ValveFit:
    """The frequency-flow table of a valve from mass measurements (module docstring).

    frequency_hz, duration_s, mass_g: (n,) one row per measurement (repeats allowed;
    frequencies within 1e-6 Hz are one frequency); density_g_cm3: the material's density;
    lines: (n,) the file's line of each run (:func:`read_mass_runs`), to name a run.
    Runs at 0 Hz check that the valve passes nothing there. The table is the polynomial
    fit at the measured frequencies; where no polynomial follows the runs within
    ``MAX_MISFIT`` or rises throughout (a valve that barely opens at its lowest
    frequencies, or saturates), the per-frequency means made to rise
    (:func:`_monotone_means`; ``method`` says which). Raises FlowError naming ``source``
    (and the run's line) when fewer than 3 distinct non-zero frequencies were measured, a
    run is further than ``REPLICATE_SPREAD`` from the other runs at its frequency, the
    valve passes flow at 0 Hz, the means do not rise with the frequency within
    ``MAX_MISFIT``, or the monotone means would end on a top frequency more than
    ``MAX_MISFIT`` above the trend of the frequencies below it (:func:`_top_trend`: a
    saturating valve flattens, it does not jump). A single run at the top frequency that
    far above that trend, which a polynomial follows, cannot be told from the valve by
    replicates: it is written, with a line in ``warnings``.
    """
    if not (density_g_cm3 > 0 and math.isfinite(density_g_cm3)):
        raise ConfigError(f"density {density_g_cm3!r} g/cm^3: must be a positive number")
    # one frequency, however it was typed (100 and 100.0000001 were written as one table
    # row, which the table's reader refused)
    f = np.round(np.asarray(frequency_hz, dtype=np.float64), 6)
    q = 1000.0 * np.asarray(mass_g, dtype=np.float64) / (density_g_cm3 *
                                                          np.asarray(duration_s, np.float64))
    on = f > 0
    freqs, inverse, counts = np.unique(f[on], return_inverse=True, return_counts=True)
    if len(freqs) < 3:
        raise FlowError(f"{source}: {len(freqs)} distinct non-zero frequencies; the thesis "
                        "measures about 20 (6.1), at least 3 are needed")
    means = np.bincount(inverse, weights=q[on]) / counts
    if not (means > 0).any():   # an SVD that did not converge (a hunt's)
        raise FlowError(f"{source}: no flow at any frequency (every run collected 0 g): "
                        "the valve did not open, or the runs were not weighed")
    # a flow this small counts as none against the table (a dead band's runs read -100 %
    # off its ~0, and were refused as "not rising")
    floor = NO_FLOW * float(means.max())
    if means.max() > MAX_VALVE_FLOW_MM3_S:
        k = int(np.argmax(means))
        raise FlowError(f"{source}: {means[k]:.4g} mm^3/s at {freqs[k]:g} Hz, more than a "
                        f"deposition valve gives ({MAX_VALVE_FLOW_MM3_S:g} mm^3/s): masses "
                        "in mg, or durations in ms? (mass_g in g, duration_s in s)")
    lines = None if lines is None else np.asarray(lines)
    # each run against its replicates, before their mean is fitted: one of three runs
    # weighed double moved its frequency's mean 33 %, which the monotone means followed
    allowance = 1000.0 * REPLICATE_BALANCE_G / (density_g_cm3 *
                                                np.asarray(duration_s, np.float64)[on])
    bad = _replicate_outlier(inverse, q[on], allowance, floor)
    if bad is not None:
        _refuse_replicate(source, lines, np.flatnonzero(on), freqs, inverse, q[on], bad)
    if not on.all():
        # the table passes nothing at 0 Hz: a tester's leaking valve (16.7 mm^3/s at 0 Hz)
        # was fitted through 0 with a residual of 0 %. Against the lowest frequency that
        # flows: a valve with a dead band (0 g up to 50 Hz) was refused for a balance's
        # 0.2 mg at 0 Hz, "3333...(300 digits) % of the flow at 10 Hz (0 mm^3/s)"
        leak = float(q[~on].mean())
        k = int(np.argmax(means > floor))   # none flows: refused below, "no flow rises"
        if means[k] > floor and leak > MAX_MISFIT * float(means[k]):
            raise FlowError(f"{source}: the runs at 0 Hz collected {leak:.4g} mm^3/s, "
                            f"{100 * leak / float(means[k]):.0f} % of the flow at "
                            f"{freqs[k]:g} Hz ({means[k]:.4g} mm^3/s), the lowest that flows: "
                            "the table passes none at 0 Hz (thesis 6.1); a leaking valve, or "
                            "runs that collected something else")
    model = _flow_polynomial(f[on], q[on])
    x = np.concatenate([[0.0], freqs])
    table = model(x)
    table[0] = 0.0
    fitted_means = table[1:]
    method = "polynomial"
    if (np.diff(_as_written(table)) <= 0).any() or \
            (np.abs(means - fitted_means) > MAX_MISFIT * np.abs(fitted_means)).any():
        method = "monotone means"
        x, table = _monotone_means(freqs, means, counts)

        def model(v, x=x, table=table):
            return np.interp(np.asarray(v, dtype=np.float64), x, table)

        fitted_means = model(freqs)
        off = np.abs(means - fitted_means) > MAX_MISFIT * np.maximum(np.abs(fitted_means),
                                                                    floor)
        if off.any():
            # the worst of them (the first was named: 14 % off where another was 25 %)
            k = int(np.argmax(np.where(off, np.abs(means - fitted_means)
                                       / np.maximum(np.abs(fitted_means), floor), -1.0)))
            raise FlowError(f"{source}: the flow does not rise with the frequency: the runs "
                            f"at {freqs[k]:g} Hz ({means[k]:.4g} mm^3/s) are "
                            f"{100 * abs(means[k] / max(fitted_means[k], 1e-300) - 1):.0f} % "
                            f"off the nearest rising table ({fitted_means[k]:.4g} mm^3/s; more "
                            f"than {100 * MAX_MISFIT:.0f} %): check those runs or the valve")
        if len(x) < 2 or (np.diff(_as_written(table)) <= 0).any():
            raise FlowError(f"{source}: no flow rises with the frequency in these runs")
    warnings: list[str] = []
    trend = _top_trend(freqs, means, floor)
    if trend is not None and means[-1] > (1.0 + MAX_MISFIT) * trend:
        # the top has no frequency above it: the monotone means' rising table follows
        # any value there (a single run 50 % high was written with a residual of 0 %)
        top = np.flatnonzero(on)[inverse == len(freqs) - 1]
        what = _top_above_trend(source, lines, top, freqs, means[-1], trend)
        if method != "polynomial":
            raise FlowError(f"{what}, and no polynomial follows the runs: a valve that "
                            "saturates flattens at its top, it does not jump; check those "
                            "runs or the valve")
        if len(top) == 1:
            # replicates that agree are the valve's; one run cannot be told from a bad one
            warnings.append(f"{what}; a single run, which the table follows: repeat it")
    fitted = model(np.where(on, f, 0.0))
    resid = np.divide(q - fitted, np.maximum(np.abs(fitted), floor), out=np.zeros_like(q),
                      where=on)
    return ValveFit(frequency_hz=x, flow_mm3_s=table, measured_hz=f, measured_mm3_s=q,
                    residual=resid, density_g_cm3=float(density_g_cm3), fit=model,
                    method=method, warnings=tuple(warnings))


def _top_above_trend(source: str, lines: np.ndarray | None, top: np.ndarray,
                     freqs: np.ndarray, mean: float, trend: float) -> str:
    """The words for a top frequency whose ``mean`` flow is above the ``trend`` of the
    frequencies below it (mm^3/s, :func:`_top_trend`); top: the indices of its runs."""
    where = _at(source, lines, int(top[0])) if len(top) == 1 else source
    runs = "the run" if len(top) == 1 else f"the {len(top)} runs"
    below = freqs[-1 - TREND_POINTS:-1]
    return (f"{where}: {runs} at the top frequency, {freqs[-1]:g} Hz, gave {mean:.4g} mm^3/s, "
            f"{100 * (mean / trend - 1):.0f} % above the trend of {below[0]:g}-{below[-1]:g} "
            f"Hz ({trend:.4g} mm^3/s there; more than {100 * MAX_MISFIT:.0f} %)")


def _refuse_replicate(source: str, lines: np.ndarray | None, runs: np.ndarray,
                      freqs: np.ndarray, inverse: np.ndarray, q: np.ndarray,
                      bad: tuple[int, float]) -> None:
    """Raise the FlowError for :func:`_replicate_outlier`'s run ``bad`` (an index into
    the non-zero runs ``runs``, (m,) indices into the file's runs; inverse, q: (m,) their
    frequencies (indices into ``freqs``, Hz) and flows, mm^3/s), naming the file, the line
    and the frequency. Of two runs neither can be told for the bad one: both are named."""
    i, med = bad
    same = np.flatnonzero(inverse == inverse[i])
    hz = f"{freqs[inverse[i]]:g} Hz"
    if len(same) == 2:
        j = int(same[same != i][0])
        a, b = sorted((i, j))
        other = (f"line {int(lines[runs[b]])}" if lines is not None else f"run {runs[b] + 1}")
        raise FlowError(f"{_at(source, lines, int(runs[a]))}: the 2 runs at {hz} ({q[a]:.4g} "
                        f"and {q[b]:.4g} mm^3/s, this one and {other}) differ by "
                        f"{100 * abs(q[a] - q[b]) / med:.0f} % of their mean (more than "
                        f"{200 * REPLICATE_SPREAD:.0f} %, where runs scatter by about 1 %): "
                        "one was weighed twice, cut short or spilt; repeat them")
    raise FlowError(f"{_at(source, lines, int(runs[i]))}: the run at {hz} ({q[i]:.4g} mm^3/s) "
                    f"is {100 * abs(q[i] / med - 1):.0f} % off the median of the "
                    f"{len(same)} runs there ({med:.4g} mm^3/s; more than "
                    f"{100 * REPLICATE_SPREAD:.0f} %, where runs scatter by about 1 %): "
                    "weighed twice, cut short or spilt? repeat or drop it")


#: A reading this far below 0, g, is a balance's drift on an empty run (a leak check at
#: 0 Hz read -0.0003 g, and the whole file was refused): it counts as 0.
BALANCE_DRIFT_G = 0.001

#: Significant digits of the table as written (:func:`format_valve_table`).
TABLE_DIGITS = 10


def _as_written(values: np.ndarray) -> np.ndarray:
    return np.array([float(f"{v:.{TABLE_DIGITS}g}") for v in values])


def format_valve_table(fit: ValveFit, material: str) -> str:
    """The table as the calibration CSV :func:`icefab.flow.load_calibration` reads."""
    lines = [f"# Valve frequency-flow table nu = h(Q) for the {material} material (thesis 6.1),",
             f"# fitted by 'icefab calibrate valve' from {len(fit.measured_hz)} mass "
             f"measurements at density {fit.density_g_cm3:g} g/cm^3;",
             f"# RMS relative residual {100 * fit.rms_residual:.2f} %.",
             "frequency_hz,flow_mm3_s"]
    lines += [f"{fv:.{TABLE_DIGITS}g},{qv:.{TABLE_DIGITS}g}"
              for fv, qv in zip(fit.frequency_hz, fit.flow_mm3_s)]
    return "\n".join(lines) + "\n"


def write_valve_table(fit: ValveFit, path: str | os.PathLike, material: str) -> None:
    write_atomic(path, format_valve_table(fit, material))


def plot_valve_fit(fit: ValveFit, path: str | os.PathLike, title: str = "") -> None:
    """The measurements, the fitted table and the relative residuals (PNG)."""
    from icefab.report import pyplot, save_figure

    plt = pyplot()
    fig, (a, b) = plt.subplots(2, 1, figsize=(7, 6), sharex=True,
                               gridspec_kw={"height_ratios": [3, 1.4]})
    xs = np.linspace(0.0, float(fit.frequency_hz[-1]), 400)
    a.plot(fit.measured_hz, fit.measured_mm3_s, "o", ms=4, label="measured")
    a.plot(xs, fit.fit(xs), "-", label="polynomial fit" if fit.method == "polynomial"
           else "monotone means (the table)")
    a.plot(fit.frequency_hz, fit.flow_mm3_s, "s", mfc="none", label="table written")
    a.set_ylabel("flow Q (mm$^3$/s)")
    a.set_title(title or "valve frequency-flow calibration (thesis 6.1)")
    a.legend(loc="upper left")
    a.grid(alpha=0.3)
    b.axhline(0.0, color="k", lw=0.8)
    b.plot(fit.measured_hz, 100 * fit.residual, "o", ms=4)
    b.set_xlabel("valve frequency (Hz)")
    b.set_ylabel("residual (%)")
    b.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, path)


# =========================================================================== synthetic data


HeightFn = Callable[[np.ndarray], np.ndarray]  # (n, 2) base-frame points, mm -> (n,) mm


def _edge(u: np.ndarray, spot_mm: float) -> np.ndarray:
    """0 -> 1 step at u = 0 blurred by a Gaussian spot of std ``spot_mm``."""
    from scipy.special import ndtr

    if spot_mm <= 0:
        return (u >= 0).astype(np.float64)
    return ndtr(u / spot_mm)


def jig_height(jig: Sequence[JigEdge], base_mm: float = 0.0, spot_mm: float = 0.05
               ) -> HeightFn:
    """The jig's elevation (base frame) as the laser sees it through a Gaussian spot."""
    def z(p: np.ndarray) -> np.ndarray:
        p = np.asarray(p, dtype=np.float64).reshape(-1, 2)
        out = np.full(len(p), float(base_mm))
        for e in jig:
            out += e.step_mm * _edge(p[:, "xy".index(e.axis)] - e.position_mm, spot_mm)
        return out
    return z


def edge_height(x0_mm: float, step_mm: float, *, skew: float = 0.0, y_ref_mm: float = 0.0,
                spot_mm: float = 0.05) -> HeightFn:
    """An object with one sharp edge x = x0 + skew * (y - y_ref), ``step_mm`` higher on
    the +x side."""
    def z(p: np.ndarray) -> np.ndarray:
        p = np.asarray(p, dtype=np.float64).reshape(-1, 2)
        return step_mm * _edge(p[:, 0] - (x0_mm + skew * (p[:, 1] - y_ref_mm)), spot_mm)
    return z


def scan_line(height: HeightFn, start_mm: Sequence[float], end_mm: Sequence[float], *,
              speed_mm_s: float, offset_mm: Sequence[float], latency_s: float,
              rate_hz: float = 100.0, accel_mm_s2: float = 500.0, noise_mm: float = 0.01,
              position_noise_mm: float = 0.005, rng: np.random.Generator,
              scan: int = 0) -> Scan:
    """A laser scan along a straight EE move from rest to rest (trapezoidal speed).

    start_mm, end_mm: EE positions in the base frame; offset_mm: the laser's TRUE offset
    from the EE; latency_s: its TRUE latency. Samples every ``1 / rate_hz`` s from a random
    phase, tagged with the EE position then (plus encoder noise ``position_noise_mm``),
    reading ``height`` at the spot where the EE was ``latency_s`` earlier plus laser noise
    ``noise_mm`` (thesis 5.2.1: 100 Hz, read out after each path).
    """
    a = np.asarray(start_mm, dtype=np.float64)
    b = np.asarray(end_mm, dtype=np.float64)
    length = float(np.linalg.norm(b - a))
    u = (b - a) / length
    v, acc = float(speed_mm_s), float(accel_mm_s2)
    t_acc = v / acc
    d_acc = 0.5 * acc * t_acc ** 2
    if 2 * d_acc > length:      # triangular profile
        t_acc = math.sqrt(length / acc)
        v = acc * t_acc
        d_acc = 0.5 * length
    t_flat = (length - 2 * d_acc) / v
    total = 2 * t_acc + t_flat

    def s_of(t: np.ndarray) -> np.ndarray:
        t = np.clip(t, 0.0, total)
        s1 = 0.5 * acc * np.minimum(t, t_acc) ** 2
        s2 = v * np.clip(t - t_acc, 0.0, t_flat)
        td = np.clip(t - t_acc - t_flat, 0.0, t_acc)
        s3 = v * td - 0.5 * acc * td ** 2
        return s1 + s2 + s3

    t = rng.uniform(0.0, 1.0 / rate_hz) + np.arange(int(total * rate_hz)) / rate_hz
    ee = a + s_of(t)[:, None] * u
    read_at = a + s_of(t - latency_s)[:, None] * u + np.asarray(offset_mm, dtype=np.float64)
    z = height(read_at) + rng.normal(0.0, noise_mm, len(t))
    tagged = ee + rng.normal(0.0, position_noise_mm, ee.shape)
    return Scan(scan=scan, t=t, xy=tagged, z=z)


def default_jig(origin_mm: Sequence[float] = (230.0, -80.0)) -> list[JigEdge]:
    """A stepped test jig: three 2 mm steps up and one 6 mm step down along x and along
    y, 10 mm apart, near ``origin_mm`` (base frame)."""
    ox, oy = map(float, origin_mm)
    edges = []
    for axis, o in (("x", ox), ("y", oy)):
        edges += [JigEdge(axis, o + 10.0 * k, 2.0) for k in range(3)]
        edges.append(JigEdge(axis, o + 30.0, -6.0))
    return edges


def synthetic_jig_scans(jig: Sequence[JigEdge], *, offset_mm: Sequence[float],
                        latency_s: float, speed_mm_s: float = 10.0, passes: int = 3,
                        spot_mm: float = 0.05, latency_jitter_s: float = 3e-4,
                        rng: np.random.Generator, **noise) -> list[Scan]:
    """Jig scans (thesis 5.2.1) with a known offset and latency: ``passes`` scans along
    each axis in each direction, 10 mm either side of the jig's edges, laser spot on the
    jig (the EE path is placed with the TRUE offset: an operator aims roughly). Per-path
    latency varies by ``latency_jitter_s`` (the C40's start delay). ``noise``: laser and
    encoder noise for :func:`scan_line`."""
    z = jig_height(jig, spot_mm=spot_mm)
    off = np.asarray(offset_mm, dtype=np.float64)
    scans = []
    for ai, axis in enumerate("xy"):
        pos = [e.position_mm for e in jig if e.axis == axis]
        if not pos:
            continue
        other = [e.position_mm for e in jig if e.axis != axis]
        across = (min(other) - 10.0) if other else 0.0   # outside the other edges' span
        lo, hi = min(pos) - 10.0, max(pos) + 10.0
        for k in range(passes):
            for sign in (1, -1):
                p0 = np.zeros(2)
                p1 = np.zeros(2)
                p0[ai], p1[ai] = (lo, hi) if sign > 0 else (hi, lo)
                p0[1 - ai] = p1[1 - ai] = across - 2.0 * k
                lat = latency_s + rng.normal(0.0, latency_jitter_s)
                scans.append(scan_line(z, p0 - off, p1 - off, speed_mm_s=speed_mm_s,
                                       offset_mm=off, latency_s=lat, rng=rng,
                                       scan=len(scans), **noise))
    return scans


def synthetic_edge_scans(*, offset_mm: Sequence[float], latency_s: float,
                         x0_mm: float = 260.0, y0_mm: float = -100.0, step_mm: float = 5.0,
                         skew: float = 0.02, paths: int = 100, spacing_mm: float = 0.5,
                         speed_mm_s: float = 50.0, length_mm: float = 40.0,
                         spot_mm: float = 0.05, latency_jitter_s: float = 3e-4,
                         rng: np.random.Generator, **noise) -> list[Scan]:
    """Parallel scans across one sharp, slightly skewed edge in alternating directions
    (thesis 5.2.1: "relatively high speed but in opposite directions"), ``spacing_mm``
    apart, with a known offset and latency."""
    z = edge_height(x0_mm, step_mm, skew=skew, y_ref_mm=y0_mm, spot_mm=spot_mm)
    off = np.asarray(offset_mm, dtype=np.float64)
    scans = []
    for k in range(paths):
        y = y0_mm + (k - 0.5 * (paths - 1)) * spacing_mm
        a = np.array([x0_mm - 0.5 * length_mm, y])
        b = np.array([x0_mm + 0.5 * length_mm, y])
        if k % 2:
            a, b = b, a
        lat = latency_s + rng.normal(0.0, latency_jitter_s)
        scans.append(scan_line(z, a - off, b - off, speed_mm_s=speed_mm_s, offset_mm=off,
                               latency_s=lat, rng=rng, scan=k, **noise))
    return scans


def synthetic_masses(flow: Callable[[np.ndarray], np.ndarray], frequencies_hz: Sequence[float],
                     *, density_g_cm3: float, duration_s: float = 60.0, repeats: int = 2,
                     balance_g: float = 0.001, scatter: float = 0.01,
                     rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mass measurements of a valve whose TRUE flow is ``flow(frequency)`` mm^3/s: each
    run collects for ``duration_s`` s; its flow scatters by ``scatter`` (relative std:
    temperature, drops left on the nozzle) and the balance reads to ``balance_g`` (std).
    Returns (frequency_hz, duration_s, mass_g) arrays, one row per run."""
    f = np.repeat(np.asarray(frequencies_hz, dtype=np.float64), repeats)
    q = np.asarray(flow(f), dtype=np.float64) * (1.0 + rng.normal(0.0, scatter, len(f)))
    mass = np.maximum(q * duration_s * density_g_cm3 / 1000.0
                      + rng.normal(0.0, balance_g, len(f)), 0.0)
    return f, np.full(len(f), float(duration_s)), mass


def write_masses(path: str | os.PathLike, frequency_hz: np.ndarray, duration_s: np.ndarray,
                 mass_g: np.ndarray) -> None:
    lines = [MASS_HEADER] + [f"{f:g},{d:g},{m:.4f}"
                             for f, d, m in zip(frequency_hz, duration_s, mass_g)]
    write_atomic(path, "\n".join(lines) + "\n")
