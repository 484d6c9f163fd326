"""Surface mapping feedback plugged into the virtual cell (thesis 5.1-5.2): the controller
of :mod:`icefab.feedback` as a :data:`~icefab.sim.cell.Controller`.
"""

from __future__ import annotations

import logging

import numpy as np

from icefab import feedback
from icefab.config import Job
from icefab.errors import GeometryError
from icefab.sim.cell import Controller, Measurement
from icefab.sim.deposition import ActionFn

log = logging.getLogger(__name__)


def smf_controller(job: "Job") -> Controller:
    """The surface mapping feedback of :mod:`icefab.feedback` as a simulator controller.

    At each measurement: the laser samples become a surface on the controller grid
    (``job.feedback.grid_mm``, Delaunay-linear, optional robust smoothing), restricted to
    the layer's merged footprint (footprint nodes outside the samples' hull take the
    nearest sample); the normalised error drives one step of the spatial PID (eq. 5.1,
    saturation and anti-windup); the returned u(xy) samples the saturated action
    (thesis 5.1-5.2). A layer whose surface cannot be formed (too few or collinear
    samples, or none on the footprint) keeps the state and applies the integral term
    alone (:func:`icefab.feedback.held_action`), with a warning; it applied 0, and the
    integral's bias of a lasting flow error was lost for an interval.
    """

    fb = job.feedback
    state = feedback.SmfState()

    def held(m: Measurement, why: str) -> ActionFn:
        action = feedback.held_action(state, job)
        log.warning("layer %d: %s; SMF keeps its state and applies the integral term "
                    "alone until the next measurement%s", m.layer, why,
                    "" if action is not None else " (none yet: nominal flow)")
        if action is None:
            return lambda xy: np.zeros(len(xy))
        return feedback.action_sampler(action)

    def control(m: Measurement) -> ActionFn:
        nonlocal state
        try:
            surf = feedback.surface_from_samples(m.samples, None, fb.grid_mm,
                                                 smoothing=fb.smoothing)
        except GeometryError as exc:
            # e.g. a tiny top layer with too few or collinear samples
            return held(m, f"no surface from {len(m.samples)} laser samples ({exc})")
        measured = feedback.restrict_to_footprint(surf, m.samples, m.footprint, m.grid)
        if not np.isfinite(measured.z).any():
            return held(m, "the laser samples miss the footprint")
        error = feedback.error_surface(measured, m.nominal_z, m.interval_mm)
        action, state = feedback.smf_update(state, error, job)
        return feedback.action_sampler(action)

    return control
