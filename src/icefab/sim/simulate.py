"""Simulating a build: a ``Toolpaths`` or ``BuildMotion`` turned into layer plans and run on
the virtual cell, open loop or with SMF (:func:`simulate_build`).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable, Sequence

import numpy as np

from icefab.config import Job
from icefab.core import BuildMotion, LayerMotion, LayerPaths, Toolpaths
from icefab.errors import SimulationError
from icefab.stages import MEASURED, PARTS, PLACEMENT, check_agrees
from icefab.motion import plan_toolpaths
from icefab.sim.cell import Controller, SimResult, run_cell
from icefab.sim.plans import _measured, measurement_layers, plan_layer, plan_layer_motion
from icefab.sim.smf import smf_controller

log = logging.getLogger(__name__)


def _chosen(build: "Toolpaths | BuildMotion", job: "Job", layers: int | None) -> tuple:
    # a program's wrong argument was an AttributeError or TypeError from deep inside
    if not isinstance(build, (Toolpaths, BuildMotion)):
        raise SimulationError(f"build: a {type(build).__name__}: expected the Toolpaths of "
                              "plan_paths or the BuildMotion of plan_toolpaths")
    if job is None or isinstance(job, (str, bytes, dict)):
        raise SimulationError(f"job = {job!r:.40}: expected an icefab.Job (None: the "
                              "build's own)")
    if layers is not None and (isinstance(layers, bool)
                               or not isinstance(layers, (int, np.integer))):
        raise SimulationError(f"layers = {layers!r}: expected a whole number (0: all)")
    n = layers if layers is not None else job.simulation.layers
    if n is not None and n < 0:
        raise SimulationError(f"layers = {n}: expected >= 0 (0: all)")
    chosen = build.layers[:n] if n else build.layers
    if not chosen:
        raise SimulationError("the build has no layers to simulate")
    return tuple(chosen)


def _has_laser(layer: "LayerPaths | LayerMotion") -> bool:
    """Whether a layer has a measurement path (trajectory) with at least one point: the
    layers :func:`plan_layer` / :func:`plan_layer_motion` give laser samples."""
    if isinstance(layer, LayerPaths):
        return any(p.role == "measure" and len(p.points) > 0 for p in layer.paths)
    return any(t.path is not None and t.path.role == "measure" and len(t.xy) > 0
               for t in layer.trajectories)


def measured_layers(build: "Toolpaths | BuildMotion", job: "Job | None" = None, *,
                    layers: int | None = None) -> list[int]:
    """Layer indices :func:`simulate_build` measures for these arguments, found without
    simulating (so that options such as a surface layer are checked up front)."""
    job = job if job is not None else getattr(build, "job", None)
    chosen = _chosen(build, job, layers)
    flags = [_has_laser(lay) for lay in chosen]
    return [chosen[j].index for j in _measured(flags, job.feedback.interval_layers)]


#: Settings trajectories and the job simulating them must agree on: where the material
#: goes (:data:`icefab.stages.PLACEMENT`: frames, tool offsets, widths, layer thickness),
#: the robot whose base frame the samples are in, which layers are measured
#: (:data:`icefab.stages.MEASURED`) and the parts they were made from
#: (:data:`icefab.stages.PARTS`): :data:`icefab.stages.DECIDED`, the part origin and the
#: robot (a job naming another robot gives it its own origin,
#: :func:`icefab.stages.overlay_job`: the refusal named the origin, not the robot).
MOTION_SETTINGS = PLACEMENT + ("cell.robot",) + MEASURED + PARTS


def check_motion_job(planned: "Job", job: "Job", source: str = "the trajectories") -> None:
    """SimulationError if ``job`` differs from the job trajectories were ``planned`` with
    in one of :data:`MOTION_SETTINGS` (:func:`icefab.stages.check_agrees`)."""
    check_agrees(planned, job, source, "icefab paths, then icefab plan",
                 settings=MOTION_SETTINGS, error=SimulationError)


def simulate_build(build: "Toolpaths | BuildMotion", job: "Job | None" = None, *,
                   layers: int | None = None, closed_loop: bool = True,
                   controller: Controller | None = None,
                   keep_surfaces: Sequence[int] | None = None,
                   progress: Callable[[int, int], None] | None = None) -> SimResult:
    """Build on the virtual cell, open loop or with surface mapping feedback.

    build: the toolpaths (``icefab.paths.plan_paths``) or their trajectories
        (``icefab.motion.plan_toolpaths`` / ``load_trajectories``); job: settings
        (default: the job the build was made with; for trajectories it must agree with
        that job on :data:`MOTION_SETTINGS`).
    With ``job.simulation.deposition = "flow"`` the commanded volume is laid along the
    paths (or the trajectories' sample chords). With ``"valves"`` every layer's
    deposition trajectories run through their valve programs, pulse by pulse
    (:func:`layer_valves`, :func:`deposit_pulses`); from toolpaths the minimum-time
    trajectories of the simulated layers are planned first
    (:func:`icefab.motion.plan_toolpaths`, ``cell.cpus`` processes) — to simulate the
    same build twice, plan once and pass the ``BuildMotion``.
    layers: simulate only the first N layers (default ``job.simulation.layers``, 0 = all).
    closed_loop: run the SMF controller (``controller``, default :func:`smf_controller`)
        after every measurement layer; False runs open loop (no control action), and so
        does a job with ``feedback.enabled = false`` (it measures nothing: ``icefab
        build`` and ``icefab simulate`` run it open loop).
    keep_surfaces: toolpaths layer indices of measurement layers whose error surfaces
        are kept in the result (for plots like thesis Fig. 5-8); default: the last
        measurement layer.
    progress: called as ``progress(done, total)`` after every layer.
    """

    job = job if job is not None else getattr(build, "job", None)
    chosen = _chosen(build, job, layers)
    if keep_surfaces is not None and (isinstance(keep_surfaces, (str, bytes)) or not all(
            isinstance(k, (int, np.integer)) and not isinstance(k, bool)
            for k in keep_surfaces)):
        raise SimulationError(f"keep_surfaces = {keep_surfaces!r}: expected layer indices")
    if isinstance(build, BuildMotion):
        if job is not build.job:
            check_motion_job(build.job, job)
        plans = [plan_layer_motion(lm, job) for lm in chosen]
    else:
        if job is not build.job and build.job is not None:
            # what the paths stage decided (a tester's toolpaths of 1 mm layers simulated
            # with a 0.5 mm job: half the volume commanded, measured at the wrong heights)
            check_agrees(build.job, job, "the toolpaths", "icefab paths",
                         error=SimulationError)
        if job.simulation.deposition == "valves":
            motion = plan_toolpaths(Toolpaths(layers=chosen, job=build.job), job)
            plans = [plan_layer_motion(lm, job) for lm in motion.layers]
        else:
            plans = [plan_layer(lp.index, lp.paths, job, lp.thickness) for lp in chosen]
    measure = measurement_layers(plans, job.feedback.interval_layers)
    if keep_surfaces is None:
        keep_surfaces = [plans[measure[-1]].index] if measure else []
    closed_loop = closed_loop and job.feedback.enabled
    if closed_loop and controller is None:
        controller = smf_controller(job)
    return run_cell(plans, job, measure_layers=measure,
                    controller=controller if closed_loop else None,
                    keep_surfaces=keep_surfaces, progress=progress)


def _simulate_task(args: tuple) -> SimResult:
    build, job, layers, closed_loop, keep = args
    return simulate_build(build, job, layers=layers, closed_loop=closed_loop,
                          keep_surfaces=keep)


def simulate_open_and_smf(build: "Toolpaths | BuildMotion", job: "Job | None" = None, *,
                          layers: int | None = None, keep_surfaces: Sequence[int] | None = None,
                          progress: Callable[[int, int], None] | None = None
                          ) -> tuple[SimResult, SimResult]:
    """:func:`simulate_build` open loop and with SMF, the two builds side by side on two
    worker processes (``cell.cpus`` permitting): they are independent runs of the same
    seeded cell, so the results are those of two calls in a row. With
    ``feedback.enabled = false`` both are the one open-loop run. progress: in builds
    (2)."""
    from icefab.parallel import parallel_map

    job = job if job is not None else getattr(build, "job", None)
    _chosen(build, job, layers)   # the arguments checked before any worker starts
    if layers:  # only the layers simulated travel to the workers (0: all)
        build = dataclasses.replace(build, layers=tuple(build.layers[:int(layers)]))
    if not job.feedback.enabled:
        run = simulate_build(build, job, layers=layers, closed_loop=False,
                             keep_surfaces=keep_surfaces, progress=progress)
        return run, run
    items = [(build, job, layers, closed, keep_surfaces) for closed in (False, True)]
    open_loop, closed = parallel_map(_simulate_task, items, job, min_items=2,
                                     progress=progress)
    return open_loop, closed
