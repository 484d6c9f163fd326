"""A layer's valve programs made at once (flow._nominal_fm_programs, issue 17) are
plan_valves' programs, bit for bit, findings and refusals included."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from icefab import Job
from icefab.core import LayerMotion, Toolpath, Trajectory
from icefab.errors import FlowError
from icefab.flow import calibration_for, plan_layer_valves, plan_valves, program_pieces
from icefab.stages import layer_height


def _trajectory(rng, n, dt, v_top, role, material, width, mismatch):
    """A wavy path with a random smooth speed profile sampled at dt; ``mismatch`` scales
    the speed array away from the distance the samples travel."""
    v = v_top * np.clip(np.sin(np.linspace(0, np.pi, n)) + rng.uniform(-0.2, 0.2, n), 0, None)
    v[0] = v[-1] = 0.0
    s = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)])
    xy = np.column_stack([340.0 + s, 2.0 * np.sin(s / 7.0)])
    path = Toolpath(points=xy.copy(), material=material, role=role, width=width, layer=2,
                    frame="base")
    return Trajectory(dt=dt, xy=xy, joints=np.zeros((n, 3)), speed=v * mismatch,
                      duration=(n - 1) * dt, path=path)


def _as_tour(rng, tr):
    """The trajectory as a continuous tour: random spans the valve is on (some shorter
    than a sample step, some ending on a sample, now and then one out of order: refused by
    name), 0 wide between them."""
    d = tr.duration
    edges = np.sort(rng.uniform(0.0, d, 2 * int(rng.integers(1, 5))))
    if rng.random() < 0.3:
        edges[0] = 0.0
    if rng.random() < 0.3:
        edges[-1] = d
    if rng.random() < 0.3:      # a span end on a sample
        edges[1] = np.round(edges[1] / tr.dt) * tr.dt
        edges = np.sort(edges)
    if rng.random() < 0.1:      # a span shorter than a step
        edges[1] = edges[0] + 0.1 * tr.dt
        edges = np.sort(edges)
    spans = edges.reshape(-1, 2)
    if rng.random() < 0.03:
        spans = spans[::-1].copy()
    if rng.random() < 0.03:     # no span at all: a tour that deposits nothing
        spans = np.zeros((0, 2))
    t = tr.t
    on = np.zeros(len(t), dtype=bool)
    for a, b in spans:
        on |= (t >= a) & (t <= b)
    w = np.where(on, tr.widths if tr.widths is not None else tr.path.width, 0.0)
    return dataclasses.replace(tr, widths=w, on_spans=spans)


def _programs_agree(a, b):
    pa, pb = program_pieces(a), program_pieces(b)
    assert len(pa) == len(pb)
    for x, y in zip(pa, pb):
        assert x.ticks.dtype == y.ticks.dtype and np.array_equal(x.ticks, y.ticks)
        assert (x.duration, x.tick_s, x.widths_us) == (y.duration, y.tick_s, y.widths_us)
    assert a.warnings == b.warnings
    # the volumes agree but for the round trip of a flow through its table's frequency
    assert (a.commanded_mm3, a.laid_mm3) == pytest.approx((b.commanded_mm3, b.laid_mm3),
                                                          rel=1e-9, abs=1e-12)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), count=st.integers(1, 12),
       high_rate=st.booleans(), short_pieces=st.booleans(), clamp=st.booleans(),
       thickness=st.sampled_from([float("nan"), 0.1, 0.6]), variable=st.booleans(),
       tours=st.booleans())
# a clamped tour: its laid volume came out 4.5 % above plan_valves' (the flow taken as
# passing as commanded where the clamp held the valve at its table's end)
@example(seed=12, count=5, high_rate=False, short_pieces=False, clamp=True, thickness=0.6,
         variable=True, tours=True)
def test_a_layer_at_once_equals_path_by_path(seed, count, high_rate, short_pieces, clamp,
                                             thickness, variable, tours):
    rng = np.random.default_rng(seed)
    job = Job().replace(**{"flow.out_of_range": "clamp" if clamp else "error"})
    if high_rate:  # pulses above one per tick: shared ticks
        job = job.replace(**{"flow.max_frequency_hz": 250.0, "flow.tick_s": 0.004})
    if short_pieces:  # programs split into pieces
        job = job.replace(**{"flow.max_piece_s": 0.5, "flow.max_pulses": 40})
    trajs = []
    for _ in range(count):
        n = int(rng.choice([1, 2, 3, 40, 400]))
        role = str(rng.choice(["fill", "boundary", "travel", "measure"]))
        trajs.append(_trajectory(rng, n, float(rng.choice([0.016, 0.008])),
                                 float(rng.choice([5.0, 60.0, 125.0, 400.0])), role,
                                 str(rng.choice(["part", "scaffold"])),
                                 float(rng.choice([0.0, 0.7, 1.5, 3.0])),
                                 float(rng.choice([1.0, 1.0, 1.0, 1.3]))))
        if variable and rng.random() < 0.5:   # a variable-width path (issue 15)
            w = rng.uniform(0.3, 3.0, len(trajs[-1].xy))
            if rng.random() < 0.05:
                w[0] = np.nan   # refused by name, as path by path
            trajs[-1] = dataclasses.replace(trajs[-1], widths=w)
        if tours and rng.random() < 0.5 and len(trajs[-1].xy) > 1:   # a continuous tour
            trajs[-1] = _as_tour(rng, trajs[-1])
    layer = LayerMotion(index=2, z=0.5, trajectories=tuple(trajs), thickness=thickness)
    dh = layer_height(thickness, job)
    want, refused = [], None
    for i, tr in enumerate(trajs):
        if not tr.path.depositing:
            continue
        try:
            want.append((i, tr.path.material, plan_valves(
                tr, tr.path.material, job, layer_thickness=dh,
                calibration=calibration_for(tr.path.material, job))))
        except FlowError as exc:
            # the layer's names the path by its index, as motion's: "layer 2, path 3
            # (part fill)", not "layer 2 part fill path"
            p = tr.path
            old = f"layer {p.layer} {p.material} {p.role} path: "
            refused = (f"layer 2, path {i} ({p.material} {p.role}): "
                       f"{str(exc).removeprefix(old)}")
            break
    if refused is not None:
        with pytest.raises(FlowError) as e:
            plan_layer_valves(layer, job)
        assert str(e.value) == refused
        return
    got = plan_layer_valves(layer, job)
    assert [(lp.path, lp.material) for lp in got] == [(i, m) for i, m, _ in want]
    for lp, (_, _, prog) in zip(got, want):
        _programs_agree(lp.program, prog)


def test_the_cases_it_hands_back_are_met():
    """The example above must reach shared ticks, pieces, findings and refusals: one of
    each, fixed."""
    rng = np.random.default_rng(7)
    job = Job().replace(**{"flow.max_piece_s": 0.5, "flow.max_pulses": 40,
                           "flow.out_of_range": "clamp"})
    trajs = [_trajectory(rng, 400, 0.016, v, "fill", mt, w, m)
             for v, mt, w, m in ((60.0, "part", 1.5, 1.0), (400.0, "part", 1.5, 1.0),
                                 (125.0, "part", 0.7, 1.0), (60.0, "part", 1.5, 1.3))]
    layer = LayerMotion(index=2, z=0.5, trajectories=tuple(trajs))
    got = plan_layer_valves(layer, job)
    text = " ".join(w for lp in got for w in lp.program.warnings)
    for finding in ("clamped (flow.out_of_range = 'clamp')", "drops per mm", "integrates to"):
        assert finding in text
    assert any(lp.program.pieces for lp in got)
    for lp, tr in zip(got, trajs):
        _programs_agree(lp.program, plan_valves(tr, tr.path.material, job))


def test_pulses_sharing_a_tick_are_counted_per_path(monkeypatch):
    """A valid FM job drives the valve at most once per tick, so pulses share a tick only
    through rounding; the count is checked on instants made to collide."""
    import icefab._pulses as kernel

    real = kernel.pulse_instants_many

    def colliding(t, nu, starts):
        times, offsets = real(t, nu, starts)
        out = times.copy()
        for i in range(len(offsets) - 1):   # every third pulse of a path onto the one before
            a, b = offsets[i], offsets[i + 1]
            out[a + 3:b:3] = out[a + 2:b - 1:3]
        return out, offsets

    monkeypatch.setattr(kernel, "pulse_instants_many", colliding)
    rng = np.random.default_rng(3)
    job = Job()
    trajs = [_trajectory(rng, n, 0.016, 60.0, "fill", "part", 1.5, 1.0) for n in (400, 2, 90)]
    got = plan_layer_valves(LayerMotion(index=2, z=0.5, trajectories=tuple(trajs)), job)
    for lp in got:
        ticks = lp.program.ticks.astype(np.int64)
        shared = int(np.count_nonzero(np.diff(ticks) == 0))
        said = [w for w in lp.program.warnings if "share a 2 ms tick" in w]
        assert shared == 0 and not said or said and said[0].split(": ")[1].startswith(
            f"{shared} pulses share")
    assert sum("share" in w for lp in got for w in lp.program.warnings) == 2


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), count=st.integers(1, 8))
def test_drop_spacing_of_a_layer_equals_path_by_path(seed, count):
    from icefab.cli.valves_cmd import _drop_spacing, _drop_spacings
    rng = np.random.default_rng(seed)
    job = Job().replace(**{"flow.max_piece_s": 0.5, "flow.out_of_range": "clamp"})
    trajs = [_trajectory(rng, int(rng.choice([1, 2, 5, 300])), 0.016,
                         float(rng.choice([2.0, 60.0, 125.0])), "fill", "part",
                         float(rng.choice([0.7, 1.5])), 1.0) for _ in range(count)]
    trajs = [_as_tour(rng, t) if len(t.xy) > 1 and rng.random() < 0.4 else t for t in trajs]
    trajs = [t for t in trajs if t.on_spans is None or
             np.all(np.diff(t.on_spans.ravel()) >= 0)]     # not the refused ones
    progs = [plan_valves(t, "part", job) for t in trajs]
    for limit in (1.0, 0.0):
        got = _drop_spacings(trajs, progs, limit)
        want = [_drop_spacing(t, p, limit) for t, p in zip(trajs, progs)]
        np.testing.assert_allclose(np.array(got), np.array(want), rtol=0, atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), count=st.integers(0, 10),
       thickness=st.sampled_from([float("nan"), 0.1, 0.6]))
def test_layer_headroom_names_the_first_fastest_widest_path_of_each_material(seed, count,
                                                                           thickness):
    from icefab.flow import trajectory_width
    from icefab.headroom import layer_headroom
    rng = np.random.default_rng(seed)
    trajs = [_trajectory(rng, int(rng.choice([1, 2, 40])), 0.016,
                         float(rng.choice([60.0, 125.0])),
                         str(rng.choice(["fill", "boundary", "travel", "measure"])),
                         str(rng.choice(["part", "scaffold"])), float(rng.choice([0.0, 1.5])),
                         1.0) for _ in range(count)]
    if count > 2:  # a tie: the first of the largest is named
        trajs.append(trajs[0])
    job = Job()
    dh = layer_height(thickness, job) * job.flow.layer_scale
    want = {}   # path by path, in order: the largest nominal flow w dh v_max of each material
    for t in trajs:
        if t.path.depositing:
            w = trajectory_width(t, t.path.material, job)
            q = w * dh * float(np.max(t.speed))
            if t.path.material not in want or q > want[t.path.material][0]:
                want[t.path.material] = (q, t.path.role, w, float(np.max(t.speed)))
    got = layer_headroom(LayerMotion(index=4, z=1.0, trajectories=tuple(trajs),
                                     thickness=thickness), job)
    assert [r.material for r in got] == sorted(want)
    for r in got:
        assert (r.nominal_mm3_s, r.role, r.width_mm, r.speed_mm_s, r.layer) == \
            (*want[r.material], 4)


def test_a_path_with_bad_widths_is_refused_in_its_turn():
    """Refusals come in path order, as plan_valves path by path gives them: a boundary
    whose flow leaves the table, then a fill with a NaN width - the boundary's message
    (the widths of a layer are checked at once; a bad one had been refused first)."""
    rng = np.random.default_rng(3)
    job = Job()
    fast = _trajectory(rng, 40, 0.016, 400.0, "boundary", "part", 3.0, 1.0)
    fill = _trajectory(rng, 40, 0.016, 60.0, "fill", "part", 1.5, 1.0)
    w = np.full(len(fill.xy), 1.5)
    w[3] = np.nan
    fill = dataclasses.replace(fill, widths=w)
    with pytest.raises(FlowError) as first:
        plan_valves(fast, "part", job, calibration=calibration_for("part", job))
    assert "outside the calibration table" in str(first.value)
    with pytest.raises(FlowError) as e:
        plan_layer_valves(LayerMotion(index=2, z=0.5, trajectories=(fast, fill)), job)
    # named by its index in the layer, as motion names paths
    assert str(e.value) == str(first.value).replace("layer 2 part boundary path: ",
                                                    "layer 2, path 0 (part boundary): ")
    with pytest.raises(FlowError, match=r"^layer 2, path 0 \(part fill\): .*widths"):
        plan_layer_valves(LayerMotion(index=2, z=0.5, trajectories=(fill, fast)), job)
