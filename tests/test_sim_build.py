"""Virtual cell: whole builds on synthetic annulus layers, open loop and closed loop.

The closed-loop tests here use a small stand-in PI controller written in this file (the
real controller is tested with the demo part in test_sim_demo.py), so they check the
simulator's loop, not the feedback module.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.interpolate import RegularGridInterpolator
from scipy.spatial import cKDTree

from icefab import Job
from icefab.sim import Measurement, SimulationError, simulate_build
from icefab.core import HeightMap, LayerPaths, Toolpath, Toolpaths

DH = 0.25


def _circle(r, n=240):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return r * np.column_stack([np.cos(t), np.sin(t)])


def annulus_toolpaths(job: Job, n_layers: int, *, measure: bool = True) -> Toolpaths:
    """Part r in [10, 25] mm, scaffold r in [25, 31] mm, tiled exactly by its paths.

    Boundaries 1.5 mm wide on each edge, fill rings 3 mm wide; measurement circles every
    3 mm on every interval_layers-th layer.
    """
    rings = [("part", "boundary", 24.25, 1.5), ("part", "boundary", 10.75, 1.5)]
    rings += [("part", "fill", r, 3.0) for r in (13.0, 16.0, 19.0, 22.0)]
    rings += [("scaffold", "boundary", 30.25, 1.5), ("scaffold", "boundary", 25.75, 1.5),
              ("scaffold", "fill", 28.0, 3.0)]
    n_d = job.feedback.interval_layers
    layers = []
    for i in range(n_layers):
        z = (i + 1) * DH
        paths = [Toolpath(points=_circle(r), z=z, material=m, role=role, closed=True, width=w,
                      layer=i) for m, role, r, w in rings]
        if measure and (i + 1) % n_d == 0:
            paths += [Toolpath(points=_circle(r), z=z, material="part" if r < 25 else "scaffold",
                           role="measure", closed=True, layer=i)
                      for r in np.arange(11.5, 30.0, 3.0)]
        layers.append(LayerPaths(index=i, z=z, paths=tuple(paths)))
    return Toolpaths(layers=tuple(layers), job=job)


def quiet_job(**changes) -> Job:
    base = {"simulation.flow_error": 0.0, "simulation.noise_mm": 0.0,
            "simulation.laser_noise_mm": 0.0, "simulation.edge_loss": 0.0,
            "simulation.debris_rate": 0.0, "simulation.laser_latency_s": 0.0,
            "simulation.spread_mm": 0.5}
    base.update(changes)
    return Job().replace(**base)


def stand_in_controller(kp=1.0, ki=0.33, sat=0.3):
    """A minimal spatial PI (thesis eq. 5.1 without D) on the simulator grid; the measured
    height of a footprint cell is that of its nearest laser sample."""
    state: dict = {"integral": None}

    def control(m: Measurement):
        xs, ys = m.grid.grid()
        iy, ix = np.nonzero(m.footprint)
        _, nearest = cKDTree(m.samples[:, :2]).query(np.column_stack([xs[ix], ys[iy]]))
        e = np.zeros(m.footprint.shape)
        e[iy, ix] = (m.nominal_z - m.samples[nearest, 2]) / m.interval_mm
        integral = e if state["integral"] is None else state["integral"] + e
        integral = np.clip(integral, -sat / ki, sat / ki)
        state["integral"] = integral
        u = np.clip(kp * e + ki * integral, -sat, sat)
        f = RegularGridInterpolator((ys, xs), u, bounds_error=False, fill_value=0.0)
        return lambda xy: f(xy[:, ::-1])

    return control


def test_without_disturbances_the_surface_sits_at_the_nominal_height():
    job = quiet_job()
    res = simulate_build(annulus_toolpaths(job, 12), job, closed_loop=False)
    assert res.layers.tolist() == [3, 7, 11]
    assert np.allclose(res.nominal_z, [1.0, 2.0, 3.0])
    # only cells near the part's edges deviate (the liquid runs towards the partly
    # covered rim: 0.3 % of the height)
    assert np.all(res.rms < 0.005 * res.nominal_z)
    assert np.all(res.rms_measured < 0.005 * res.nominal_z)
    assert res.volume_deposited == pytest.approx(res.volume_commanded, rel=1e-9)
    # commanded volume is the annulus area times the layer thickness (paths tile it)
    area = np.pi * (31.0 ** 2 - 10.0 ** 2)
    assert res.volume_commanded == pytest.approx(12 * DH * area, rel=0.005)


def test_open_loop_error_grows_with_height_under_a_flow_error():
    job = quiet_job(**{"simulation.flow_error": 0.10})
    res = simulate_build(annulus_toolpaths(job, 24), job, closed_loop=False)
    assert np.all(np.diff(res.rms) > 0)
    # the whole surface is 10 % too high: rms = 0.1 * nominal height
    assert np.allclose(res.rms, 0.1 * res.nominal_z, rtol=0.02)
    xs, ys = res.height.grid()
    r = np.hypot(*np.meshgrid(xs, ys))
    # away from the rims, where the liquid runs towards the partly covered outermost cells
    assert np.allclose(res.height.z[(r > 12.5) & (r < 28.5)], 1.1 * 24 * DH, rtol=5e-3)


@pytest.mark.parametrize("flow_error", [-0.5, -0.9])
def test_a_valve_that_gives_a_fraction_of_its_flow_is_measured_and_corrected(flow_error):
    """Under -90 % flow no cell reached a quarter of the layer, so no layer had a footprint:
    the RMS was NaN and SMF had no samples on it, exactly where the error is worst. What
    counts as covered scales with the valves' gain: the error is the missing ice, and SMF
    raises the flow as far as its saturation lets it."""
    job = quiet_job(**{"simulation.flow_error": flow_error})
    tp = annulus_toolpaths(job, 8)
    open_ = simulate_build(tp, job, closed_loop=False)
    assert np.isfinite(open_.rms).all()
    # the whole surface is short by the flow error (the edges lose nothing: quiet job)
    assert np.allclose(open_.rms, -flow_error * open_.nominal_z, rtol=0.02)
    smf = simulate_build(tp, job)
    assert np.isfinite(smf.rms).all() and smf.rms[-1] < open_.rms[-1]


def test_flow_gain_drifts_with_the_volume_through_each_valve():
    job = quiet_job(**{"simulation.flow_drift_per_cm3": 0.02})
    res = simulate_build(annulus_toolpaths(job, 8), job, closed_loop=False)
    part_cm3 = 8 * DH * np.pi * (25.0 ** 2 - 10.0 ** 2) / 1000
    assert res.flow_gain[0] == pytest.approx(1 + 0.02 * part_cm3, rel=0.01)
    assert res.volume_deposited > res.volume_commanded


def test_a_valve_drifting_down_stops_and_takes_nothing_away():
    # a drift of -0.1 per cm^3 made the flow gain negative: the valve took ice away and the
    # surface went 12 mm below the platform (a tester's)
    job = quiet_job(**{"simulation.flow_drift_per_cm3": -0.1})
    res = simulate_build(annulus_toolpaths(job, 30), job, closed_loop=False)
    part_cm3 = np.pi * (25.0 ** 2 - 10.0 ** 2) / 1000 * DH    # a layer's part: 10 cm^3 in 25
    assert 30 * part_cm3 > 10.0 and res.flow_gain[0] == 0.0
    assert np.nanmin(res.height.z) >= 0.0 and res.volume_deposited > 0.0
    assert res.volume_deposited < res.volume_commanded


def test_height_noise_keeps_its_size_whatever_its_correlation_length():
    # the smoothed field was divided by its spread with its mean left on: at a correlation
    # length near the grid's size, 0.02 mm of noise became metres (noise_corr_mm = 100)
    from icefab.sim.cell import _noise_field

    rng = np.random.default_rng(0)
    for sigma in (0.0, 3.0, 50.0, 200.0):
        f = _noise_field(rng, (150, 150), sigma)
        assert abs(f.mean()) < (0.1 if sigma == 0.0 else 1e-9) and f.std() == \
            pytest.approx(1.0, rel=0.05)
    job = quiet_job(**{"simulation.noise_mm": 0.02, "simulation.noise_corr_mm": 100.0})
    res = simulate_build(annulus_toolpaths(job, 8), job, closed_loop=False)
    assert np.nanmax(np.abs(res.rms)) < 0.2


def test_edge_loss_lowers_the_region_edges_only():
    job = quiet_job(**{"simulation.edge_loss": 0.2})
    res = simulate_build(annulus_toolpaths(job, 8), job, closed_loop=False)
    xs, ys = res.height.grid()
    X, Y = np.meshgrid(xs, ys)
    r = np.hypot(X, Y)
    z = res.height.z
    assert np.allclose(z[(r > 16) & (r < 20)], 8 * DH, rtol=5e-3)  # interior untouched
    edge = (r > 10.0) & (r < 10.3)  # within a fifth of a path width of the hole's edge
    # (the liquid levels part of the loss: it runs from the interior towards the edge)
    assert np.all(z[edge] < 8 * DH * (1 - 0.2 * 0.3))
    assert res.volume_deposited < res.volume_commanded


def test_noise_and_debris_disturb_the_surface_reproducibly():
    job = quiet_job(**{"simulation.noise_mm": 0.02, "simulation.debris_rate": 1.0})
    tp = annulus_toolpaths(job, 8)
    a = simulate_build(tp, job, closed_loop=False)
    b = simulate_build(tp, job, closed_loop=False)
    assert np.array_equal(a.height.z, b.height.z, equal_nan=True)
    assert a.max_abs[-1] > 0.1  # a debris bump of 0.5 mm somewhere
    c = simulate_build(tp, job.replace(**{"simulation.seed": 7}), closed_loop=False)
    assert not np.array_equal(a.height.z, c.height.z, equal_nan=True)


def test_stand_in_controller_removes_a_flow_error():
    job = quiet_job(**{"simulation.flow_error": 0.10, "simulation.noise_mm": 0.02,
                       "simulation.laser_noise_mm": 0.01, "simulation.edge_loss": 0.1,
                       "simulation.laser_latency_s": 0.002})
    tp = annulus_toolpaths(job, 32)
    open_ = simulate_build(tp, job, closed_loop=False)
    closed = simulate_build(tp, job, controller=stand_in_controller(), keep_surfaces=[31])
    assert closed.closed_loop and not open_.closed_loop
    assert closed.rms[-1] < open_.rms[-1] / 5
    assert 31 in closed.surfaces
    surf = closed.surfaces[31]
    assert surf.z.shape == closed.height.z.shape


def test_without_measurement_paths_the_laser_reads_along_the_deposition_paths():
    job = quiet_job(**{"simulation.flow_error": 0.1})
    res = simulate_build(annulus_toolpaths(job, 8, measure=False), job, closed_loop=False)
    assert res.layers.tolist() == [3, 7]
    assert res.rms_measured[-1] == pytest.approx(0.1 * 2.0, rel=0.05)


def test_layers_limit_and_errors():
    job = quiet_job()
    tp = annulus_toolpaths(job, 12)
    assert simulate_build(tp, job, layers=8, closed_loop=False).n_layers == 8
    with pytest.raises(SimulationError, match="layers"):
        simulate_build(tp, job, layers=-1, closed_loop=False)
    with pytest.raises(SimulationError, match="no layers"):
        simulate_build(Toolpaths(layers=(), job=job), job, closed_loop=False)
    empty = Toolpaths(layers=(LayerPaths(index=0, z=0.25, paths=()),), job=job)
    with pytest.raises(SimulationError, match="nothing to deposit"):
        simulate_build(empty, job, closed_loop=False)


def test_the_real_smf_controller_closes_the_loop_on_the_annulus():
    # icefab.feedback behind simulate_build's default controller (thesis 5.1-5.2)
    job = quiet_job(**{"simulation.flow_error": 0.10, "simulation.noise_mm": 0.02,
                       "simulation.laser_noise_mm": 0.01, "simulation.spread_mm": 1.0})
    tp = annulus_toolpaths(job, 24)
    open_ = simulate_build(tp, job, closed_loop=False)
    smf = simulate_build(tp, job)
    assert smf.rms[-1] < open_.rms[-1] / 4
    assert smf.rms_measured[-1] < 0.1


def test_a_job_that_measures_nothing_runs_open_loop_through_the_api_too():
    """feedback.enabled = false: 'icefab build' and 'icefab simulate' run open loop, and so
    do simulate_build and simulate_open_and_smf (they ran SMF on the laser along the
    deposition paths: a hunt's 0.059 mm against 0.191 mm open loop). layers=0 is every
    layer in both (simulate_open_and_smf said the build had no layers)."""
    from icefab.sim import simulate_open_and_smf

    job = quiet_job(**{"simulation.flow_error": 0.1, "feedback.enabled": False})
    tp = annulus_toolpaths(job, 8, measure=False)
    open_ = simulate_build(tp, job, closed_loop=False)
    smf = simulate_build(tp, job)
    assert smf.closed_loop is False and smf.rms[-1] == open_.rms[-1] > 0.15
    a, b = simulate_open_and_smf(tp, job, layers=0)
    assert a.n_layers == b.n_layers == 8 and b.rms[-1] == open_.rms[-1]
    on = job.replace(**{"feedback.enabled": True})
    a, b = simulate_open_and_smf(annulus_toolpaths(on, 8), on, layers=0)
    assert a.n_layers == 8 and b.rms[-1] < a.rms[-1] / 2


def test_a_debris_pulse_is_a_bump_of_the_configured_height_and_radius():
    job = quiet_job(**{"simulation.debris_rate": 0.3, "simulation.debris_height_mm": 0.5,
                       "simulation.debris_radius_mm": 2.0})
    tp = annulus_toolpaths(job, 12)
    res = simulate_build(tp, job, closed_loop=False)
    flat = simulate_build(tp, quiet_job(), closed_loop=False)
    bump = res.height.z - flat.height.z
    assert np.nanmin(bump) >= -1e-12
    peak = np.nanmax(bump)
    assert 0.45 < peak < 0.5 * (1 + 12 * 0.3 + 3)  # at least one whole bump, few overlap
    # each bump holds 2 pi r^2 h of volume (less where it hangs over the footprint's edge)
    n_cells_half = np.count_nonzero(bump > 0.25)
    assert n_cells_half * 0.25 > 0.5 * np.pi * (2.0 * np.sqrt(2 * np.log(2))) ** 2


def test_smf_controller_skips_a_measurement_it_cannot_map(caplog):
    from icefab.sim import smf_controller

    job = quiet_job()
    control = smf_controller(job)
    grid = HeightMap(origin=np.zeros(2), spacing=0.5, z=np.ones((4, 4)))
    m = Measurement(layer=3, k=1, nominal_z=1.0, interval_mm=1.0,
                    samples=np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]]),
                    footprint=np.ones((4, 4), dtype=bool), grid=grid)
    u = control(m)
    assert np.array_equal(u(np.zeros((5, 2))), np.zeros(5))
    assert "layer 3" in caplog.text


def test_the_c_controller_corrects_as_well():
    # speed c_nom / (1 + u) lays (1 + u) times the volume per mm, like the nu-controller;
    # its saturation planes keep the speed within +-30 % (thesis 5.2.2)
    job = quiet_job(**{"simulation.flow_error": 0.10, "feedback.controller": "speed"})
    tp = annulus_toolpaths(job, 16)
    open_ = simulate_build(tp, job, closed_loop=False)
    smf = simulate_build(tp, job)
    assert smf.rms[-1] < open_.rms[-1] / 3


def test_paths_the_simulator_cannot_use_are_named():
    job = quiet_job()
    bad = [Toolpath(points=_circle(20.0), z=0.25, role="fill", closed=True, width=3.0,
                frame="base"),
           Toolpath(points=np.array([[0.0, 0.0], [np.nan, 1.0]]), z=0.25, role="fill", width=3.0)]
    for path, msg in zip(bad, ["'base' frame", "NaN"]):
        tp = Toolpaths(layers=(LayerPaths(index=5, z=0.25, paths=(path,)),), job=job)
        with pytest.raises(SimulationError, match=f"layer 5: .*{msg}"):
            simulate_build(tp, job, closed_loop=False)
    # width 0 (Toolpath's default): its material's, as the valve programs take it (the
    # simulator refused it while plan_valves laid it at the fill width, a hunt's)
    runs = []
    for w in (0.0, job.materials.part.fill_width_mm):
        path = Toolpath(points=_circle(20.0), z=0.25, role="fill", closed=True, width=w)
        tp = Toolpaths(layers=(LayerPaths(index=0, z=0.25, paths=(path,)),), job=job)
        runs.append(simulate_build(tp, job, closed_loop=False))
    assert runs[0].volume_commanded == runs[1].volume_commanded > 0


def test_the_calibrated_latency_is_taken_off_the_lasers_own():
    # a build takes cell.laser_latency_s off what the laser reads (icefab.build), the
    # virtual cell's laser lags by simulation.laser_latency_s; the simulator ignored the
    # calibrated value (a tester's 0.05 s gave the same RMS), so it measured otherwise
    base = {"simulation.flow_error": 0.10, "simulation.edge_loss": 0.1}

    def closed(**changes):
        job = quiet_job(**base, **changes)
        res = simulate_build(annulus_toolpaths(job, 12), job, controller=stand_in_controller())
        return res.rms.tolist(), res.rms_measured.tolist()

    none = closed()
    assert closed(**{"simulation.laser_latency_s": 0.05, "cell.laser_latency_s": 0.05}) == none
    lagging = closed(**{"simulation.laser_latency_s": 0.05})
    assert lagging != none
    # overstated by the calibration: the samples read ahead of their tags, as a build does
    assert closed(**{"cell.laser_latency_s": 0.05}) not in (none, lagging)


def test_toolpaths_simulated_with_a_job_that_contradicts_them_are_refused():
    # a tester's toolpaths of 1 mm layers simulated with a 0.5 mm job: half the volume
    # commanded and the heights measured wrong, without a word (trajectories were checked)
    job = quiet_job(**{"slicing.layer_thickness_mm": DH})
    tp = annulus_toolpaths(job, 4)
    other = job.replace(**{"slicing.layer_thickness_mm": 2 * DH})
    with pytest.raises(SimulationError, match="slicing.layer_thickness_mm"):
        simulate_build(tp, other, closed_loop=False)
    # settings the paths stage did not decide may differ
    simulate_build(tp, job.replace(**{"simulation.flow_error": 0.05}), closed_loop=False)


def test_the_error_over_the_whole_footprint_shows_what_the_part_rms_leaves_out():
    """A control review's: ridges where beads overlap, in the scaffold or where the two
    materials meet, stayed out of the part's RMS (the part inside its rim). The result
    and the command's table and rms.csv give the RMS and the largest error over the whole
    footprint, part and scaffold, beside it: the error surface SMF regulates."""
    from icefab.cli.simulate_cmd import (HEADER, final_footprint_line, format_table,
                                         table_rows)

    job = quiet_job()
    tp = annulus_toolpaths(job, 24, measure=False)
    # the scaffold's outer boundary 0.5 mm into its fill: a third of a bead too much there
    layers = tuple(dataclasses.replace(lay, paths=tuple(
        dataclasses.replace(p, points=_circle(29.75)) if p.material == "scaffold"
        and p.role == "boundary" and np.hypot(*p.points[0]) > 30 else p
        for p in lay.paths)) for lay in tp.layers)
    res = simulate_build(dataclasses.replace(tp, layers=layers), job, closed_loop=False,
                         keep_surfaces=[23])
    assert res.layers.tolist() == [3, 7, 11, 15, 19, 23]
    assert res.rms[-1] < 0.005 * res.nominal_z[-1]          # the part: at its height
    assert res.rms_footprint[-1] > 10 * res.rms[-1]          # the scaffold: not
    assert res.max_abs_footprint[-1] > 0.1 * res.nominal_z[-1]
    assert np.all(np.diff(res.rms_footprint) > 0)            # and it grows
    e = res.surfaces[23].z
    assert res.rms_footprint[-1] == pytest.approx(np.sqrt(np.nanmean(e ** 2)), rel=1e-12)
    assert res.max_abs_footprint[-1] == pytest.approx(np.nanmax(np.abs(e)), rel=1e-12)
    rows = table_rows(res, res)
    assert dict(zip(HEADER, rows[-1]))["rms_footprint_smf_mm"] == res.rms_footprint[-1]
    lines = format_table(rows)
    assert "all open" in lines[0] and len(lines[-2].split()) == 8
    assert final_footprint_line(res, res).startswith(
        f"over the whole footprint (part and scaffold), layer 23: RMS "
        f"{res.rms_footprint[-1]:.3f} mm open loop")


def test_adaptive_layers_normalise_the_error_by_the_interval_the_action_acts_over():
    """Thesis 5.1.3 and eq. 5.11c: U_k is applied to the layers up to the next measurement,
    which lay (1 + u) dh_m, so E_k is normalised by that interval. The simulator took the
    height built before the measurement: a layer laid twice (0.1 mm too high) under
    0.1 mm layers, then 0.4 mm ones, asked 0.1 / 0.4 of the flow off a 1.6 mm interval
    and left the part 0.3 mm low instead of at its height (Kp = 1: one step)."""
    from icefab.sim import smf_controller

    job = quiet_job(**{"feedback.kp": 1.0, "feedback.ki": 0.0, "feedback.kd": 0.0})
    tp = annulus_toolpaths(job, 12, measure=False)
    thick = [0.1] * 4 + [0.4] * 4 + [0.25] * 4
    layers = []
    for lay, t in zip(tp.layers, thick):
        paths = lay.paths * 2 if lay.index == 0 else lay.paths    # laid twice: +0.1 mm
        layers.append(dataclasses.replace(lay, paths=paths, thickness=t))
    tp = dataclasses.replace(tp, layers=tuple(layers))
    seen = []
    smf = smf_controller(job)

    def control(m: Measurement):
        seen.append((m.layer, m.nominal_z, m.interval_mm))
        return smf(m)

    res = simulate_build(tp, job, controller=control)
    assert [(k, round(z, 9)) for k, z, _ in seen] == [(3, 0.4), (7, 2.0), (11, 3.0)]
    # the interval each action is applied over: to the next measurement, then the step
    # the measurements follow (4 x 0.25 mm)
    assert [d for _, _, d in seen] == pytest.approx([1.6, 1.0, 1.0])
    # the open loop keeps the extra 0.1 mm; SMF takes it off in one interval
    open_loop = simulate_build(tp, job, closed_loop=False)
    assert open_loop.rms[1] == pytest.approx(0.1, abs=0.01)
    assert res.rms[0] == pytest.approx(0.1, abs=0.01) and res.rms[1] < 0.02


def test_a_layer_without_a_surface_keeps_the_integral_term_acting(caplog):
    """A control review's: a measurement whose samples form no surface (collinear here)
    applied u = 0 for the next interval, and the integral's bias of the +10 % flow
    error was lost. Now the state is kept and the integral term alone acts (thesis
    5.1.2: not measured is not error 0), with a warning."""
    import logging

    from icefab.sim import smf_controller

    # P and D off: the action of a measurement is its integral term
    job = quiet_job(**{"simulation.flow_error": 0.10, "feedback.kp": 0.0,
                       "feedback.kd": 0.0})
    tp = annulus_toolpaths(job, 12)
    line = Toolpath(points=np.array([[-20.0, 0.5], [20.0, 0.5]]), z=8 * DH, material="part",
                    role="measure", closed=False, layer=7)
    layers = list(tp.layers)
    layers[7] = dataclasses.replace(layers[7], paths=tuple(
        p for p in layers[7].paths if p.role != "measure") + (line,))
    tp = dataclasses.replace(tp, layers=tuple(layers))
    smf = smf_controller(job)
    actions = []

    def control(m: Measurement):
        actions.append(smf(m))
        return actions[-1]

    with caplog.at_level(logging.WARNING, logger="icefab.sim.smf"):
        simulate_build(tp, job, controller=control)
    assert len(actions) == 3
    pts = np.array([[17.5, 0.0], [0.0, -17.5], [-28.0, 0.0], [0.0, 28.0]])
    first, held = actions[0](pts), actions[1](pts)
    assert np.all(first < -0.02)          # the part stood 10 % high: less flow
    np.testing.assert_allclose(held, first, rtol=1e-12)    # held, not 0
    assert "layer 7: no surface from" in caplog.text and "integral term alone" in caplog.text
