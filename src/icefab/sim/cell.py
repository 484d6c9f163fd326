"""The run loop of the virtual cell: layer after layer, deposit, let the liquid flow, add
disturbances, measure with the laser and ask a controller for the next action
(:func:`run_cell`). It works on :class:`~icefab.sim.plans.LayerPlan` s and a controller callable,
so a build runner can drive it layer by layer from outside.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Callable, Iterable, Sequence

import numpy as np
from scipy import ndimage

from icefab.config import Job, SimulationSettings
from icefab.core import HeightMap
from icefab.errors import SimulationError
from icefab.stages import layer_height
from icefab.workload import check_grid
from icefab.sim.deposition import ActionFn, _splat, empty_surface, level_liquid
from icefab.sim.laser import laser_measure
from icefab.sim.plans import LayerPlan, layer_valves, valve_segments

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Measurement:
    """What the cell hands to the controller at a measurement layer (thesis 5.1.1).

    layer: toolpaths layer index just deposited; k: measurement count, 1 for the first.
    nominal_z: nominal height of the surface, mm (from the platform).
    interval_mm: measurement interval dh_m, mm, the height the action is applied over:
        n_d * dh; with adaptive layers the nominal height from this measurement layer to
        the next one (after the last: ``interval_layers * layer_thickness_mm``, the step
        the measurement layers follow). Thesis 5.1.3 and eq. 5.11c: U_k acts on the layers
        up to the next measurement, which lay (1 + u) dh_m; E_k normalised by the height
        built before the measurement asked 1.6 / 0.4 = 4 times the correction over an
        interval four times as tall.
    samples: (m, 3) float64, mm, laser samples (x, y, z).
    footprint: (ny, nx) bool on the simulator grid ``grid``: the merged (part + scaffold)
        footprint of the layer.
    grid: the simulator grid (its ``z`` is the nominal-height plane, NaN outside).
    """

    layer: int
    k: int
    nominal_z: float
    interval_mm: float
    samples: np.ndarray
    footprint: np.ndarray
    grid: HeightMap


Controller = Callable[[Measurement], ActionFn | None]


@dataclass(frozen=True, eq=False)
class SimResult:
    """Outcome of a simulated build, one entry per measurement layer.

    layers: (m,) int64 toolpaths layer index of each measurement layer.
    nominal_z: (m,) float64, mm, nominal surface height there.
    rms: (m,) float64, mm, RMS deviation of the true surface from nominal over the part
        footprint of that layer (the thesis' sigma_l*, Fig. 5-9); NaN when the layer
        holds no part.
    max_abs: (m,) float64, mm, largest absolute deviation over the part footprint.
    rms_measured: (m,) float64, mm, RMS of the laser samples' deviation from nominal.
    rms_footprint, max_abs_footprint: (m,) float64, mm, the RMS and largest absolute
        deviation over the layer's whole deposited footprint, part and scaffold (less its
        partly covered outermost cells): the surface SMF regulates (thesis 5.1.2). ``rms``
        leaves out the scaffold and the part's rim, where the beads of the two materials
        meet: ridges there (a bead overlap stacked layer after layer) showed in neither
        ``rms`` nor ``max_abs``.
    height: final surface; NaN where nothing was ever deposited.
    surfaces: error surfaces (true height - nominal, NaN outside the merged footprint and
        on its partly covered outermost cells) at the layers asked for, by toolpaths
        layer index.
    closed_loop: whether the controller ran.
    volume_commanded, volume_deposited: mm^3 over the build (deposited includes the flow
        error, drift, edge loss and control action).
    flow_gain: final flow gain of each valve (part, scaffold), drift included.
    n_layers: layers simulated.
    pulses: valve pulses deposited (``deposition = "valves"``; 0 with ``"flow"``).
    findings: ``(layer index, text)`` of every valve-limit finding of the programs run
        (``deposition = "valves"``), e.g. what ``flow.out_of_range = "clamp"`` clamped
        and the volume it cost (``icefab.findings.clamped_volume``).
    """

    layers: np.ndarray
    nominal_z: np.ndarray
    rms: np.ndarray
    max_abs: np.ndarray
    rms_measured: np.ndarray
    rms_footprint: np.ndarray
    max_abs_footprint: np.ndarray
    height: HeightMap
    surfaces: dict[int, HeightMap]
    closed_loop: bool
    volume_commanded: float
    volume_deposited: float
    flow_gain: tuple[float, float]
    n_layers: int
    pulses: int = 0
    findings: tuple[tuple[int, str], ...] = ()

    def as_dict(self) -> dict:
        """JSON-ready figures (no surfaces)."""
        return {"closed_loop": self.closed_loop, "n_layers": self.n_layers,
                "layers": self.layers.tolist(), "nominal_z_mm": self.nominal_z.tolist(),
                "rms_mm": self.rms.tolist(), "max_abs_mm": self.max_abs.tolist(),
                "rms_measured_mm": self.rms_measured.tolist(),
                "rms_footprint_mm": self.rms_footprint.tolist(),
                "max_abs_footprint_mm": self.max_abs_footprint.tolist(),
                "volume_commanded_mm3": self.volume_commanded,
                "volume_deposited_mm3": self.volume_deposited,
                "flow_gain": list(self.flow_gain), "pulses": self.pulses}


def grid_for(plans: Iterable[LayerPlan], job: "Job") -> HeightMap:
    """The empty surface over every deposition point of ``plans`` (walked once: a stream
    of plans is never held, e.g. the virtual cell's grid for a 1 M-facet build) with a
    margin of two path widths and two grid cells."""
    lo = hi = None
    wmax = 0.0
    for p in plans:
        for pts in (p.a, p.b):
            if len(pts):
                a, b = pts.min(axis=0), pts.max(axis=0)
                lo = a if lo is None else np.minimum(lo, a)
                hi = b if hi is None else np.maximum(hi, b)
        if len(p.half_width):
            wmax = max(wmax, float(p.half_width.max()))
    if lo is None:
        raise SimulationError("nothing to deposit: the layers have no boundary or fill paths "
                              "(or trajectories)")
    margin = 2 * wmax + 2 * job.simulation.grid_mm
    check_grid(lo - margin, hi + margin, job.simulation.grid_mm, "simulation.grid_mm")
    return empty_surface(lo, hi, job.simulation.grid_mm, margin)


def _noise_field(rng: np.random.Generator, shape: tuple[int, int], sigma_cells: float
                 ) -> np.ndarray:
    """Zero-mean, unit-std Gaussian random field with correlation length ``sigma_cells``."""
    f = rng.standard_normal(shape)
    if sigma_cells > 0.5:
        f = ndimage.gaussian_filter(f, sigma_cells, mode="wrap")
        # the filter keeps the draw's mean and shrinks its spread: with a correlation
        # length near the grid's size, dividing the spread out without taking the mean
        # off made a 0.02 mm noise a 1.2 m offset (a tester's noise_corr_mm = 100)
        f -= f.mean()
        sd = f.std()
        if sd > 0:
            f /= sd
    return f


def flow_gain(sim: SimulationSettings, used_cm3: np.ndarray | float) -> np.ndarray:
    """The valve's actual flow over the commanded (thesis 5.6, eq. 5.29): ``(1 +
    flow_error) (1 + flow_drift_per_cm3 V)`` after ``used_cm3`` V through it, never below
    0: a valve whose flow drifts down stops (a drift of -0.1 took ice away and dug below
    the platform)."""
    return (1.0 + sim.flow_error) * np.maximum(
        1.0 + sim.flow_drift_per_cm3 * np.asarray(used_cm3, dtype=np.float64), 0.0)


def _edge_factor(layer_z: np.ndarray, thresh: float, width: float, spacing: float,
                 loss: float) -> np.ndarray:
    """1 - loss within one path width of the edge of the deposited area, ramping to 1."""
    mask = layer_z > thresh
    d = ndimage.distance_transform_edt(mask) * spacing  # distance to the nearest outside cell
    ramp = np.clip(1.0 - (d - 0.5 * spacing) / width, 0.0, 1.0)
    return 1.0 - loss * ramp


def commanded_footprint(plan: LayerPlan, job: Job, thickness: float = float("nan")
                        ) -> tuple[np.ndarray, HeightMap]:
    """The cells a layer's commanded beads cover, part and scaffold: (mask (ny, nx) bool,
    its grid: a HeightMap whose origin and spacing, mm, place it; its z is 0).

    plan: the layer's :class:`~icefab.sim.LayerPlan` (its deposition segments, part
    frame); thickness: the layer's own, mm (NaN: the job's). The beads are laid on a grid
    of half the error surface's pitch (``feedback.grid_mm / 2``), and a cell is covered
    where they lay a quarter of the layer's thickness or more: :func:`deposit_layer`'s
    footprint without its disturbances. The build runner restricts its measured surface
    to it, as the simulator does to its own (``icefab.feedback.restrict_to_footprint``).
    """
    spacing = 0.5 * job.feedback.grid_mm
    if not len(plan.a):
        return np.zeros((1, 1), dtype=bool), HeightMap(np.zeros(2), spacing, np.zeros((1, 1)))
    pts = np.concatenate([plan.a, plan.b])
    grid = empty_surface(pts.min(axis=0), pts.max(axis=0), spacing,
                         float(plan.half_width.max()) + spacing)
    z = np.zeros_like(grid.z)
    _splat(z, grid.origin, spacing, plan.a, plan.b, plan.volume, plan.half_width, plan.n0,
           plan.n1, plan.ext)
    dh = layer_height(thickness, job) * job.flow.layer_scale
    return z > 0.25 * dh, grid


def deposit_layer(z: np.ndarray, origin: np.ndarray, spacing: float, segments: tuple,
                  used_cm3: np.ndarray, midpoints: np.ndarray, job: "Job", dh: float,
                  rng_noise: np.random.Generator, rng_debris: np.random.Generator
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """One layer of the virtual cell, from its deposition segments to the height it adds:
    the step :func:`run_cell` and the virtual cell's process (``icefab.cell.world``) both
    take, so they cannot drift apart.

    z: (ny, nx) current surface, mm (read, not changed); origin (2,) and spacing: its grid,
    mm. segments: ``(a, b, volume, half_width, material, n0, n1, ext)`` as
    :func:`valve_segments` or a :class:`LayerPlan` give them (volumes mm^3 as commanded).
    used_cm3: (2,) volume already through each valve, cm^3, updated in place (the flow
    drift of thesis 6.4 grows with it). midpoints: (m, 2) mm where debris may land (the
    layer's segments). dh: the layer's thickness, mm (what counts as covered: a quarter of
    it, times the valves' lowest flow gain in the layer when that is under 1: a valve that
    gives a tenth of its flow still covers the layer's footprint, thinly, and the laser
    and SMF must see it there). The generators are advanced exactly as the sequential
    simulator does.

    Returns ``(layer_img (2, ny, nx) per material before levelling, added (ny, nx) mm,
    mask (ny, nx) bool cells the layer covers, cover mm: the depth that counts as
    covered)``; the caller adds ``added`` to ``z``.
    """
    from scipy import ndimage

    sim = job.simulation
    a, b, v_all, hw, mat_of, n0, n1, ext = segments
    g = spacing
    layer_img = np.zeros((2,) + z.shape)
    edge_width = max(job.materials.part.path_width_mm, job.materials.scaffold.path_width_mm)
    low_gain = 1.0
    for mat in (0, 1):
        sel = mat_of == mat
        if not sel.any():
            continue
        v_cmd = v_all[sel]
        # flow gain with drift by valve use (thesis 6.4): volume already through the valve
        before = used_cm3[mat] + (np.cumsum(v_cmd) - v_cmd) / 1000.0
        gain = flow_gain(sim, before)
        used_cm3[mat] += v_cmd.sum() / 1000.0
        low_gain = min(low_gain, float(gain.min()))
        vol = v_cmd * gain
        _splat(layer_img[mat], origin, g, a[sel], b[sel], vol, hw[sel], n0[sel], n1[sel],
               ext[sel])
    # under a flow error of -90 % nothing reached a quarter layer: every layer had no
    # footprint, the error no RMS (NaN) and SMF no samples on it, where the error is worst
    cover = 0.25 * dh * max(low_gain, 0.0)
    if sim.edge_loss > 0:
        # liquid runs off free edges: the edge of the merged footprint (outer rim and
        # holes), not the part/scaffold interface where the materials support each other
        layer_img *= _edge_factor(layer_img[0] + layer_img[1], cover, edge_width, g,
                                  sim.edge_loss)
    added = layer_img[0] + layer_img[1]
    mask = added > cover
    if sim.spread_mm > 0:
        added = level_liquid(z, added, g, sim.spread_mm)
        mask |= added > cover
    if sim.noise_mm > 0 and mask.any():
        added += sim.noise_mm * mask * _noise_field(rng_noise, z.shape, sim.noise_corr_mm / g)
    if sim.debris_rate > 0 and len(midpoints):
        n_debris = rng_debris.poisson(sim.debris_rate)
        if n_debris:
            where = midpoints[rng_debris.integers(0, len(midpoints), n_debris)]
            # Gaussian bumps on the layer's footprint (thesis 5.6: d_pulse), each summed
            # over a +-4 sigma window: impulses at the debris cells, filtered
            impulse = np.zeros(z.shape)
            ix = np.clip(np.rint((where[:, 0] - origin[0]) / g).astype(np.int64),
                         0, z.shape[1] - 1)
            iy = np.clip(np.rint((where[:, 1] - origin[1]) / g).astype(np.int64),
                         0, z.shape[0] - 1)
            np.add.at(impulse, (iy, ix), 1.0)
            sigma = sim.debris_radius_mm / g
            bumps = ndimage.gaussian_filter(impulse, sigma, mode="constant", truncate=4.0)
            added += mask * sim.debris_height_mm * 2 * np.pi * sigma ** 2 * bumps
    return layer_img, added, mask, cover


def run_cell(plans: Sequence[LayerPlan], job: "Job", *, measure_layers: Sequence[int],
             controller: Controller | None = None, keep_surfaces: Sequence[int] = (),
             progress: Callable[[int, int], None] | None = None) -> SimResult:
    """Deposit ``plans`` layer by layer on the virtual cell, measuring and controlling.

    plans: the layers to deposit, bottom first (:func:`plan_layer`, or
        :func:`plan_layer_motion` for trajectories).
    measure_layers: positions in ``plans`` (0-based) after which the surface is measured.
    controller: called with a :class:`Measurement` after each measurement layer; returns
        the control action u(xy) applied to every segment until the next measurement
        (None: keep nominal flow). Without a controller the build runs open loop. With
        ``simulation.deposition = "valves"`` the action re-plans the valve programs of the
        next ``feedback.interval_layers`` layers (:func:`layer_valves`), whose pulses are
        then deposited (the plans must come from :func:`plan_layer_motion`).
    keep_surfaces: toolpaths layer indices whose error surfaces are kept.
    """
    sim = job.simulation
    dh = job.slicing.layer_thickness_mm
    n_d = job.feedback.interval_layers
    # adaptive layers (own thicknesses): heights add up layer by layer, and a measurement's
    # interval is the height its action is applied over, up to the next measurement
    # (uniform: (j + 1) dh, n_d dh)
    own = [layer_height(p.thickness, job) for p in plans]
    adaptive = any(math.isfinite(p.thickness) for p in plans)
    heights = np.cumsum(own) if adaptive else None
    order = sorted(int(i) for i in measure_layers)
    next_measured = dict(zip(order, order[1:]))
    step_mm = n_d * job.slicing.layer_thickness_mm
    valves = sim.deposition == "valves"
    if valves:
        for plan in plans:
            if len(plan.paths) and not plan.trajectories:
                raise SimulationError(
                    f"layer {plan.index}: simulation.deposition = 'valves' needs the "
                    "layer's trajectories (plan_layer_motion, or simulate_build, which plans "
                    "them); this plan was made from paths (plan_layer)")
    surface = grid_for(plans, job)
    z = surface.z
    g = surface.spacing
    ever = np.zeros(z.shape, dtype=bool)
    rng_noise = np.random.default_rng([sim.seed, 1])
    rng_debris = np.random.default_rng([sim.seed, 2])
    rng_laser = np.random.default_rng([sim.seed, 3])
    used_cm3 = np.zeros(2)
    measure_set = set(int(i) for i in measure_layers)
    keep = set(int(i) for i in keep_surfaces)
    action: ActionFn | None = None
    rows: list[tuple[float, ...]] = []
    surfaces: dict[int, HeightMap] = {}
    vol_cmd_total = 0.0
    vol_dep_total = 0.0
    pulses = 0
    findings: list[tuple[int, str]] = []
    k = 0
    for j, plan in enumerate(plans):
        if adaptive:
            dh = own[j]
            nominal = float(heights[j])
        else:
            nominal = (j + 1) * dh
        vol_cmd_total += float(plan.volume.sum())
        if valves:
            # thesis 5.1.3: a measurement's action goes into the valve programs of the
            # layers after it; planned when the layer's turn comes (the action only
            # changes at a measurement, so this is the program re-planned there)
            lv = layer_valves(plan, job, action)
            a, b, v_all, hw, mat_of, n0, n1, ext, n_p = valve_segments(lv, job)
            pulses += n_p
            findings += [(plan.index, w) for prog in lv.programs for w in prog.warnings]
        else:
            u = np.zeros(len(plan.volume))
            if action is not None and len(plan.volume):
                u = np.asarray(action(plan.midpoints), dtype=np.float64)
                u = np.where(np.isfinite(u), u, 0.0)
            v_all = plan.volume * np.clip(1.0 + u, 0.0, None)
            a, b, hw, mat_of = plan.a, plan.b, plan.half_width, plan.material
            n0, n1, ext = plan.n0, plan.n1, plan.ext
        layer_img, added, mask, cover = deposit_layer(
            z, surface.origin, g, (a, b, v_all, hw, mat_of, n0, n1, ext), used_cm3,
            plan.midpoints, job, dh, rng_noise, rng_debris)
        vol_dep_total += float((layer_img[0] + layer_img[1]).sum() * g * g)
        # part cells wholly inside this layer's part deposit (not the partly covered rim)
        part_mask = ndimage.binary_erosion(layer_img[0] > cover)
        if not part_mask.any():  # a part narrower than two cells: keep its rim
            part_mask = layer_img[0] > cover
        z += added
        ever |= mask
        if j in measure_set:
            k += 1
            err = z - nominal
            if part_mask.any():
                e = err[part_mask]
                rms = float(np.sqrt(np.mean(e ** 2)))
                mx = float(np.abs(e).max())
            else:
                rms = mx = float("nan")
            # the whole footprint, part and scaffold, less its partly covered rim
            inner = ndimage.binary_erosion(mask)
            foot = inner if inner.any() else mask
            ef = err[foot]
            rms_all = float(np.sqrt(np.mean(ef ** 2))) if len(ef) else float("nan")
            mx_all = float(np.abs(ef).max()) if len(ef) else float("nan")
            tagged, true = plan.laser_tagged, plan.laser_true
            if len(tagged) == 0:
                # no measurement paths in this layer: read along the deposition segments
                tagged = true = plan.midpoints
            samples = laser_measure(surface, tagged, true, noise_mm=sim.laser_noise_mm,
                                    rng=rng_laser)
            rms_meas = float(np.sqrt(np.mean((samples[:, 2] - nominal) ** 2))) \
                if len(samples) else float("nan")
            rows.append((plan.index, nominal, rms, mx, rms_meas, rms_all, mx_all))
            log.debug("layer %d (%.2f mm): RMS %.4f mm, max %.4f mm, measured RMS %.4f mm, "
                      "footprint RMS %.4f mm, max %.4f mm", plan.index, nominal, rms, mx,
                      rms_meas, rms_all, mx_all)
            if plan.index in keep:
                # without the partly covered outermost cells of the footprint
                surfaces[plan.index] = HeightMap(origin=surface.origin.copy(), spacing=g,
                                                 z=np.where(inner, err, np.nan))
            if controller is not None:
                plane = np.where(mask, nominal, np.nan)
                if not adaptive:
                    interval = n_d * dh
                elif j in next_measured:
                    interval = float(heights[next_measured[j]]) - nominal
                else:
                    interval = step_mm
                action = controller(Measurement(
                    layer=plan.index, k=k, nominal_z=nominal, interval_mm=interval,
                    samples=samples, footprint=mask,
                    grid=HeightMap(origin=surface.origin.copy(), spacing=g, z=plane)))
        if progress is not None:
            progress(j + 1, len(plans))
    arr = np.array(rows, dtype=np.float64).reshape(-1, 7)
    final = HeightMap(origin=surface.origin.copy(), spacing=g, z=np.where(ever, z, np.nan))
    gains = tuple(float(flow_gain(sim, c)) for c in used_cm3)
    return SimResult(layers=arr[:, 0].astype(np.int64), nominal_z=arr[:, 1], rms=arr[:, 2],
                     max_abs=arr[:, 3], rms_measured=arr[:, 4], rms_footprint=arr[:, 5],
                     max_abs_footprint=arr[:, 6], height=final,
                     surfaces=surfaces, closed_loop=controller is not None,
                     volume_commanded=vol_cmd_total, volume_deposited=vol_dep_total,
                     flow_gain=gains, n_layers=len(plans),  # type: ignore[arg-type]
                     pulses=pulses, findings=tuple(findings))
