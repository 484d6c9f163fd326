"""The virtual cell: a build simulator for surface mapping feedback (thesis 5.3, 5.6-5.7).

What it models
--------------
* **Deposition.** The part and the scaffold share one height map ``z (ny, nx)`` on a fine
  grid (``job.simulation.grid_mm``). Every deposition path is cut into segments; a segment
  spreads its volume uniformly over the piece of strip of the path width that it sweeps,
  cut at its ends on the bisectors of its joints (mitre joins), so a path leaves an even
  strip without overlaps or gaps at its corners. Each cell gets the exact area of its
  overlap (polygon clipping, numba) and the weights are normalised per segment, so the
  volume is conserved to rounding. A straight path deposited with flow ``q`` at speed
  ``v`` leaves a strip of width ``w`` and height ``q / (w v)``.
* **Commanded volume** (``job.simulation.deposition = "flow"``, the default: an ideal
  valve). With variable-flow valve control the valve follows the speed so that the volume
  per millimetre is ``w * dh * c`` (thesis eq. 6.2, ``c`` = ``job.flow.layer_scale``),
  whatever the speed profile. This mode therefore does not need the trajectories: it
  follows each path's own polyline (what the robot follows),
  with every edge longer than one time step at the constant speed of its role (boundary
  ``job.motion.boundary_speed_mm_s``, fill ``job.motion.fill_speed_mm_s``, times
  ``job.motion.dt_s``) split, so that the control action is applied at least once per
  time step, and gives each segment the volume ``w * dh * c * length``. (Sampling the
  paths themselves at dt instead would deposit along 2 mm chords whose seams between
  neighbouring rings leave systematic gaps that grow layer after layer.)
* **Valve pulses** (``job.simulation.deposition = "valves"``, thesis Ch. 6): the build
  runs as the cell runs it, on its minimum-time trajectories (``icefab.motion``, variable
  speed, at rest at split corners; planned here from toolpaths, or read from a
  ``trajectories.npz``) and their valve programs (:func:`icefab.flow.replan_valves`: the
  frequency follows the speed, eq. 6.2-6.6, pulse instants in 2 ms ticks, the control
  action applied). Each pulse drops the calibrated volume per pulse at its frequency
  (``Q / nu`` from the table nu = h(Q); PWM: in proportion to the pulse width) at the
  nozzle's position at the pulse instant (the trajectory interpolated in time), and the
  drop is spread over the path width along the strip between the midpoints to its
  neighbouring drops (:func:`deposit_pulses`): drops evenly spaced along the path leave
  an even strip, crowded drops a higher one. So pulse quantisation (whole pulses, 2 ms
  ticks) at variable speed shows in the surface.
* **Liquid flow.** Before it freezes, the liquid of a layer flows downhill over the frozen
  surface for a diffusion length ``spread_mm`` (:func:`level_liquid`): it fills gaps
  between paths narrower than about twice that and evens out single drops, but does not
  run off the footprint.
* **Disturbances** (thesis 5.6, eq. 5.29), drawn from ``job.simulation.seed`` so an
  open-loop and a closed-loop run see the same ones: the actual flow is the commanded flow
  times ``(1 + flow_error) * (1 + flow_drift_per_cm3 * V)`` (the drift's factor never below
  0: a failing valve stops), ``V`` the volume in cm^3 that valve has already deposited
  (the thesis saw up to +20 %, Ch. 6.4; the setting's name is kept for compatibility, its
  unit is per cm^3; with valve pulses it multiplies every drop); correlated random height
  noise per layer; debris pulses (Gaussian bumps, Poisson number per layer); weaker
  deposition within one path width of the free edges of each layer's deposit
  (``edge_loss``: the outer rim and the holes of the merged part + scaffold footprint;
  not the part/scaffold interface).
* **Laser** (thesis 5.2.1): samples at ``laser_rate_hz`` along the measurement paths at the
  measurement speed (along the measurement trajectories, in time, when the build runs on
  trajectories), with Gaussian noise and the latency a build leaves uncompensated
  (``simulation.laser_latency_s`` less the calibrated ``cell.laser_latency_s`` the build
  takes off, :func:`icefab.sim.laser.uncompensated_latency_s`): a sample tagged with the
  position at time ``t`` reads the surface where the laser was at ``t - latency``.
* **Control** (thesis 5.1.3, 5.2.2): with ``deposition = "flow"`` the nu-controller
  scales the flow of every segment by ``1 + u`` evaluated at the segment's midpoint, and
  the c-controller (speed ``1 / (1 + u)``, the same volume per millimetre) gives the same
  surface. With ``"valves"`` the action goes where the cell puts it: after each
  measurement the valve programs of the next n_d layers are re-planned with it
  (:func:`icefab.flow.replan_valves`: flow x (1 + u), or re-timed trajectories for the
  c-controller), and the surface gets what their pulses deliver.

The package, one module per concern, so the virtual cell can be driven from outside (a
build runner steps :func:`run_cell` with its own plans and controller):

* :mod:`icefab.sim.deposition` — the deposition kernels (:func:`deposit`,
  :func:`deposit_pulses`, :func:`level_liquid`), on plain arrays;
* :mod:`icefab.sim.laser` — the laser model (:func:`laser_positions`, :func:`laser_measure`);
* :mod:`icefab.sim.plans` — layer plans from toolpaths or trajectories (:func:`plan_layer`,
  :func:`plan_layer_motion`) and the valve programs the cell runs (:func:`layer_valves`);
* :mod:`icefab.sim.cell` — the run loop (:func:`run_cell`, :class:`Measurement`,
  :class:`SimResult`) over plans and a controller callable;
* :mod:`icefab.sim.smf` — the surface mapping feedback of :mod:`icefab.feedback` as a
  controller (:func:`smf_controller`);
* :mod:`icefab.sim.simulate` — :func:`simulate_build` (and :func:`simulate_open_and_smf`, the
  two runs side by side): a ``Toolpaths`` or a
  ``BuildMotion`` prepared and run open loop or with SMF.

Everything public is importable from ``icefab.sim`` as before the split.

Heights are measured from the build platform (z = 0 before the first simulated layer); the
nominal top of the j-th simulated layer (j = 0, 1, ...) is ``(j + 1) * dh``.
"""

from __future__ import annotations

from icefab.errors import SimulationError
# the layer step and grid the virtual cell's process shares (icefab.cell.world), and
# private blocks the build runner's in-process model cell reuses (icefab.runcell)
from icefab.sim.cell import (Controller, Measurement, SimResult, _edge_factor,  # noqa: F401
                             _noise_field, commanded_footprint, deposit_layer, grid_for,
                             run_cell)
from icefab.sim.deposition import (MATERIAL_ID, ActionFn, _splat, deposit,  # noqa: F401
                                   deposit_pulses, empty_surface, level_liquid, pulse_drops,
                                   pulse_segments)
from icefab.sim.laser import laser_measure, laser_positions, sample_surface
from icefab.sim.plans import (LayerPlan, LayerValves, laser_in_time, layer_valves,
                              measurement_layers, plan_layer, plan_layer_motion,
                              valve_segments)
from icefab.sim.simulate import (MOTION_SETTINGS, check_motion_job, measured_layers,
                                 simulate_build, simulate_open_and_smf)
from icefab.sim.smf import smf_controller

__all__ = ["SimulationError", "Controller", "Measurement", "SimResult", "run_cell",
           "commanded_footprint", "deposit_layer", "grid_for", "laser_in_time",
           "MATERIAL_ID", "ActionFn", "deposit", "deposit_pulses", "empty_surface",
           "level_liquid", "pulse_drops", "pulse_segments", "laser_measure", "laser_positions",
           "sample_surface", "LayerPlan", "LayerValves", "layer_valves", "measurement_layers",
           "plan_layer", "plan_layer_motion", "valve_segments", "MOTION_SETTINGS",
           "check_motion_job", "measured_layers", "simulate_build", "simulate_open_and_smf",
           "smf_controller"]
