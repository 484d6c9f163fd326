"""Surface mapping feedback plugged into the virtual cell (thesis 5.1-5.2): the controller
of :mod:`icefab.feedback` as a :data:`~icefab.sim.cell.Controller`.
"""

from __future__ import annotations

import logging

import numpy as np

from icefab import feedback
from icefab.config import Job
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

    state = feedback.SmfState()

    def control(m: Measurement) -> ActionFn:
        nonlocal state
        state, action, held = feedback.measured_update(
            state, m.samples, m.nominal_z, m.interval_mm, job, (m.footprint, m.grid))
        if held is not None:
            log.warning("layer %d: %s", m.layer, held)
        if action is None:
            return lambda xy: np.zeros(len(xy))
        return feedback.action_sampler(action)

    return control
