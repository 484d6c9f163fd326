"""The feedback's headroom: can the valves give what surface mapping feedback may ask?

SMF corrects the next layers' flow by the control action u, saturated at
``feedback.saturation`` (thesis 5.3, eq. 5.14: |u| <= U_max, 30 % by default). So along a
path the valve must be able to give ``(1 + saturation) x`` the nominal flow
``q_nom = w dh_d c`` (thesis eq. 6.2) -- inside the calibration table nu = h(Q) (6.1) and at
a frequency the cell can make (``flow.max_frequency_hz``, one pulse per tick, and
``1 / flow.calibration_pulse_ms``). On a path whose nominal flow fits but whose corrected
flow does not, the valve saturates the correction (thesis 5.2.2, :func:`icefab.flow.
valve_frequency`): the controller has less authority there than ``feedback.saturation``
says. This module finds such paths from the planned trajectories (or, before motion is
planned, from the speed bound) so plan, valves, simulate and build can say so before
anything runs.

FM only: in PWM the frequency is fixed and the flow per pulse is bounded by the period; the
PWM limits are applied per pulse by ``icefab.flow.plan_valves``.

May import: ``icefab.flow``, ``icefab.core``, ``icefab.errors``,
``icefab.resultfiles`` (the trajectories as their file stores them), numpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterable, Sequence

import numpy as np

from icefab.core import offsets
from icefab.errors import FlowError
from icefab.flow import (calibration_for, max_valve_frequency, sample_widths,
                         trajectory_width, valve_flow_range, variable_widths)

if TYPE_CHECKING:
    from icefab.config import Job
    from icefab.core import LayerMotion, Trajectory


@dataclass(frozen=True)
class Headroom:
    """The tightest path of one material.

    material; layer (index, -1 when from the speed bound); role; width_mm; speed_mm_s (the
    path's highest; a variable-width path's width and speed where w c is largest);
    nominal_mm3_s (w dh c at that speed); needed_mm3_s (nominal x (1 +
    saturation)); limit_mm3_s (the highest flow the valve gives: the calibration table at
    the cell's highest frequency); max_speed_mm_s (the highest speed at which the
    corrected flow fits); thickness_mm (the layer thickness of the nominal flow: that
    layer's own with adaptive layers).
    """

    material: str
    layer: int
    role: str
    width_mm: float
    speed_mm_s: float
    nominal_mm3_s: float
    needed_mm3_s: float
    limit_mm3_s: float
    max_speed_mm_s: float
    thickness_mm: float

    @property
    def fits(self) -> bool:
        return self.needed_mm3_s <= self.limit_mm3_s * (1 + 1e-12)

    def message(self, job: "Job") -> str:
        """One line naming the path, the flows and the settings that change them."""
        where = (f"layer {self.layer} {self.material} {self.role} path" if self.layer >= 0
                 else f"{self.material} {self.role} paths at motion.speed_mm_s")
        return (f"feedback headroom: SMF may raise the flow by feedback.saturation = "
                f"{job.feedback.saturation:.0%} to {self.needed_mm3_s:.4g} mm^3/s on the "
                f"{where} ({self.nominal_mm3_s:.4g} mm^3/s nominal = {self.width_mm:g} mm x "
                f"{self.thickness_mm:g} mm x {self.speed_mm_s:.4g} mm/s), above "
                f"the {self.limit_mm3_s:.4g} mm^3/s the valve gives at its highest frequency "
                f"({_top_frequency(self.material, job)}): " + (
                    f"there the valve saturates SMF's correction at +"
                    f"{self.limit_mm3_s / self.nominal_mm3_s - 1.0:.0%} (thesis 5.2.2)"
                    if self.nominal_mm3_s <= self.limit_mm3_s else
                    "its nominal flow is beyond the valve already (flow.out_of_range)")
                + f"; for SMF's full range keep the speed below {self.max_speed_mm_s:.4g} mm/s "
                "(motion.speed_mm_s) or lower feedback.saturation")


def _limit_flow(material: str, job: "Job") -> float:
    return valve_flow_range(calibration_for(material, job), job)[1]


def _top_frequency(material: str, job: "Job") -> str:
    """Where the valve's flow range ends (FM): the cell's highest frequency or, below it,
    the calibration table's last row (a tester's table ending at 3 Hz was said to be read
    at 500 Hz)."""
    top = float(calibration_for(material, job).frequency_hz[-1])
    cell = max_valve_frequency(job)
    if job.flow.mode != "fm":
        from icefab.flow import pwm_longest_text, pwm_max_width_ms
        longest = pwm_max_width_ms(calibration_for(material, job), job)
        return (f"{job.flow.pwm_frequency_hz:g} Hz PWM, "
                f"{pwm_longest_text(longest, 1000.0 / job.flow.pwm_frequency_hz)}")
    if top < cell:
        return (f"{top:g} Hz, the last row of materials.{material}.calibration_file's table; "
                f"the cell goes to {cell:g} Hz")
    return f"{cell:g} Hz, flow.max_frequency_hz, in the calibration table"


def feedback_headroom(trajectories: Iterable[tuple[int, "Trajectory"]], job: "Job"
                      ) -> list[Headroom]:
    """The tightest depositing path of each material (see :class:`Headroom`).

    trajectories: ``(layer index, Trajectory)`` pairs, or ``(layer index, Trajectory,
    layer thickness mm)`` for adaptive layers (a thick layer needs more flow); a
    trajectory's ``speed (n,)`` mm/s and its path's material, role and width are used
    (a variable-width one's sample of largest ``w * c``; travel and measurement paths
    deposit nothing and are skipped).
    """
    picked = [(int(layer), t, (own[0] if own else job.slicing.layer_thickness_mm)
               * job.flow.layer_scale)
              for layer, t, *own in trajectories
              if t.path is not None and t.path.depositing and len(t.speed)]
    if not picked:
        return []
    # each trajectory's top speed over all the samples at once (a bunny layer has 466
    # trajectories: one ``max`` call each cost ``icefab valves`` 3 s)
    n = np.array([len(t.speed) for _, t, _ in picked])
    vmax = np.maximum.reduceat(np.concatenate([np.asarray(t.speed, np.float64)
                                               for _, t, _ in picked]),
                               offsets(n)[:-1])
    w = np.array([trajectory_width(t, t.path.material, job) for _, t, _ in picked])
    var = [k for k, (_, t, _) in enumerate(picked) if t.widths is not None]
    if var and not _variable_peaks([picked[k][1] for k in var], var, w, vmax):
        for k in var:   # a variable-width path: its largest w * c, and there
            t = picked[k][1]
            ws = sample_widths(t, t.path.material, job)
            i = int(np.argmax(ws * np.asarray(t.speed, np.float64)))
            w[k], vmax[k] = ws[i], float(t.speed[i])
    dh = np.array([d for *_, d in picked])
    q = w * dh * vmax
    materials = np.array([t.path.material for _, t, _ in picked])
    out = []
    for m in sorted(set(materials.tolist())):
        mine = np.flatnonzero(materials == m)
        k = int(mine[np.argmax(q[mine])])        # the first of the largest
        layer, t, _ = picked[k]
        out.append(_headroom(m, float(q[k]), layer, t.path.role, float(w[k]), float(vmax[k]),
                             job, dh=float(dh[k])))
    return out


def _variable_peaks(trajs: list, var: list[int], w: np.ndarray, vmax: np.ndarray) -> bool:
    """For the variable-width trajectories ``trajs`` (``var``: their places in ``w`` and
    ``vmax``): the width and speed at the sample of largest ``w * c`` (the first of equals,
    as ``argmax``), all at once (a bunny layer has some 150). False, with nothing
    written, when some widths (:func:`icefab.flow.variable_widths`) or speeds are not one
    number per sample, or a speed is NaN: the caller goes path by path (and
    :func:`icefab.flow.sample_widths` names a path with bad widths)."""
    ok, W = variable_widths(trajs)
    speeds = [np.asarray(t.speed, np.float64) for t in trajs]
    if not ok.all() or any(v.shape != (len(t.xy),) for v, t in zip(speeds, trajs)):
        return False
    V = np.concatenate(speeds)
    P = W * V
    lens = np.array([len(v) for v in speeds])
    seg = np.repeat(np.arange(len(trajs)), lens)
    hit = np.flatnonzero(P == np.maximum.reduceat(P, offsets(lens)[:-1])[seg])
    _segs, first = np.unique(seg[hit], return_index=True)
    if len(first) != len(trajs):   # a NaN speed: argmax's rule path by path
        return False
    at = hit[first]
    w[var], vmax[var] = W[at], V[at]
    return True


def layer_headroom(layer: "LayerMotion", job: "Job") -> list[Headroom]:
    """:func:`feedback_headroom` of one layer's trajectories, at the layer's own thickness
    (:func:`icefab.stages.layer_height`)."""
    from icefab.stages import layer_height

    h = layer_height(layer.thickness, job)
    return feedback_headroom(((layer.index, t, h) for t in layer.trajectories), job)


def stored_layer_headroom(layer: "LayerMotion", job: "Job") -> list[Headroom]:
    """:func:`layer_headroom` of the layer as its trajectory file will give it back
    (:func:`icefab.resultfiles.as_stored`: speeds at 0.01 mm/s, variable widths at 0.1
    um), from which the valve programs are made: a command that plans trajectories and
    writes them (plan, build) says what ``icefab valves`` will say of the file (a
    review's +18 % and +17 %: the headroom is a ratio of flows, and its last digit
    turned on the file's rounding)."""
    from icefab.resultfiles import as_stored

    return layer_headroom(as_stored(layer), job)


def tightest(rooms: Iterable[Headroom]) -> list[Headroom]:
    """The tightest of several :func:`feedback_headroom` results (e.g. one per layer of a
    build planned as a stream), one per material: the largest nominal flow."""
    worst: dict[str, Headroom] = {}
    for r in rooms:
        if r.material not in worst or r.nominal_mm3_s > worst[r.material].nominal_mm3_s:
            worst[r.material] = r
    return [worst[m] for m in sorted(worst)]


def speed_bound_headroom(job: "Job") -> list[Headroom]:
    """The same check before motion is planned: every material's fill (the widest path)
    at the speed bound ``motion.speed_mm_s``."""
    dh = job.slicing.layer_thickness_mm * job.flow.layer_scale
    v = job.motion.speed_mm_s
    out = []
    for m in ("part", "scaffold"):
        w = max(job.materials[m].fill_width_mm, job.materials[m].path_width_mm)
        out.append(_headroom(m, w * dh * v, -1, "fill", w, v, job))
    return out


def _headroom(material: str, q: float, layer: int, role: str, w: float, v: float,
              job: "Job", dh: float | None = None) -> Headroom:
    s = job.feedback.saturation
    limit = _limit_flow(material, job)
    if dh is None:
        dh = job.slicing.layer_thickness_mm * job.flow.layer_scale
    return Headroom(material=material, layer=layer, role=role, width_mm=w, speed_mm_s=v,
                    nominal_mm3_s=q, needed_mm3_s=q * (1 + s), limit_mm3_s=limit,
                    max_speed_mm_s=limit / ((1 + s) * w * dh),
                    thickness_mm=dh / job.flow.layer_scale)


def beyond_valve(rooms: Iterable[Headroom]) -> list[Headroom]:
    """Those of ``rooms`` whose nominal flow the valve cannot give even without SMF's
    correction (beyond its flow at its highest frequency)."""
    return [r for r in rooms if r.nominal_mm3_s > r.limit_mm3_s * (1.0 + 1e-9)]


def beyond_valve_refusal(over: Sequence[Headroom], job: "Job") -> str:
    """One line refusing a build whose paths ``over`` (:func:`beyond_valve` of each
    layer's :func:`layer_headroom`, in build order) ask the valve for more than it gives:
    the first layer's path, how many layers have one, and the speed under which every one
    fits (the build named the tightest layer's path and its speed; a user fixing the file
    starts at the first: a review's)."""
    r = over[0]
    layers = len({o.layer for o in over})
    speed = min(o.max_speed_mm_s for o in over) * (1.0 + job.feedback.saturation)
    more = f" (the first of {layers} layers with such a path)" if layers > 1 else ""
    return (f"layer {r.layer} {r.material} {r.role} path: its nominal flow "
            f"{r.nominal_mm3_s:.4g} mm^3/s ({r.width_mm:g} mm x {r.thickness_mm:g} mm x "
            f"{r.speed_mm_s:.4g} mm/s) is above the {r.limit_mm3_s:.4g} mm^3/s the valve gives "
            f"at its highest frequency{more}: keep the speed below {speed:.4g} mm/s "
            "(motion.speed_mm_s), or set flow.out_of_range = 'clamp' to clamp and report "
            "instead")


def headroom_findings(rooms: Iterable[Headroom], job: "Job") -> list[str]:
    """One line for each path among ``rooms`` whose nominal flow fits the valve but whose
    flow with SMF's full correction does not: there the valve programs hold the flow at
    the valve's capacity (:func:`icefab.flow.valve_frequency`), so the correction has less
    room than ``feedback.saturation``. FM only, and only when ``feedback.enabled`` with
    the flow controller: the speed controller (``feedback.controller = "speed"``, thesis
    5.1.3) slows the robot instead and keeps the valve at the nominal flow, so it asks the
    valve for no more (it was warned all the same: a false alarm). A warning, not a
    refusal: the build runs. A nominal flow beyond the valve is not a headroom matter: the
    valve programs' own error names that path (:mod:`icefab.flow`)."""
    fb = job.feedback
    if not fb.enabled or fb.controller != "flow" or job.flow.mode != "fm":
        return []
    return [r.message(job) for r in rooms if not r.fits and r.nominal_mm3_s <= r.limit_mm3_s]


def check_slowest_flow(job: "Job") -> None:
    """Refuse, before slicing, a job whose nominal flow cannot be made even on the slowest
    depositing paths: every material's boundary at ``motion.boundary_speed_mm_s`` with
    its path width and the largest layer thickness needs ``w dh c`` (eq. 6.2) within the
    calibration table, else FlowError naming the settings (FM; under
    ``flow.out_of_range = "clamp"`` the valve programs clamp instead, and nothing is
    refused). Faster paths need more, and the valve programs name those."""
    if job.flow.mode != "fm" or job.flow.out_of_range != "error":
        return
    sl = job.slicing
    dh = (max(sl.layer_thickness_mm, sl.max_layer_thickness_mm) if sl.cusp_height_mm > 0
          else sl.layer_thickness_mm) * job.flow.layer_scale
    v = job.motion.boundary_speed_mm_s
    for m in ("part", "scaffold"):
        w = job.materials[m].path_width_mm
        q = w * dh * v
        limit = _limit_flow(m, job)
        if q > limit * (1 + 1e-12):
            raise FlowError(
                f"the {m} boundary needs {q:.4g} mm^3/s (materials.{m}.path_width_mm = "
                f"{w:g} mm x slicing.layer_thickness_mm = {dh / job.flow.layer_scale:g} mm x "
                f"motion.boundary_speed_mm_s = {v:g} mm/s, thesis eq. 6.2), more than the "
                f"valve's {limit:.4g} mm^3/s at its highest frequency "
                f"({_top_frequency(m, job)}): thinner layers, narrower paths or slower boundaries (or "
                "flow.out_of_range = 'clamp')")
