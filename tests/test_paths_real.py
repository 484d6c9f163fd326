"""Scaffold and path invariants on the demo mug and the real meshes (sliced by
icefab.slicing), measured with shapely."""
from __future__ import annotations

import numpy as np
import pytest

from icefab.config import Job
from icefab.paths import plan_layer
from icefab.regions import add_scaffold
from test_paths import check_layer_paths
from test_regions import check_invariants


def _sliced(mesh, job):
    from icefab.slicing import slice_mesh
    return slice_mesh(mesh, job)


def _check_stack(stack, job, path_layers):
    # min_width 0: the surround must be whole; default: support must still be whole
    check_invariants(add_scaffold(stack, job.replace(**{"scaffold.min_width_mm": 0.0})), 3.3)
    scaffolded = add_scaffold(stack, job)
    check_invariants(scaffolded, None)
    n = len(scaffolded)
    for k in sorted({int(round(f * (n - 1))) for f in path_layers}):
        layer = scaffolded.layers[k]
        check_layer_paths(layer, plan_layer(layer, job), job)
    return scaffolded


def test_demo_mug_invariants():
    from icefab.demo import demo_mug

    job = Job().replace(**{"slicing.layer_thickness_mm": 2.5, "cell.cpus": 1})
    stack = _sliced(demo_mug(), job)
    scaffolded = _check_stack(stack, job, (0.0, 0.3, 0.5, 0.75, 1.0))
    # the handle's lower arc overhangs: scaffold under it down to the bed
    assert scaffolded.layers[0].scaffold.area > 500


@pytest.mark.slow
# (teapot.obj is left out: its spout intersects the body, so its slices overlap)
@pytest.mark.parametrize("name", ["stanford-bunny.obj", "rocker-arm.obj", "fandisk.obj"])
def test_real_mesh_invariants(mesh_dir, name):
    from icefab.mesh import load_mesh, transform

    job = Job().replace(**{"slicing.layer_thickness_mm": 2.0, "cell.cpus": 1})
    mesh = load_mesh(mesh_dir / name)
    scale = 60.0 / float(np.ptp(mesh.vertices[:, 2]))
    job = job.replace(**{"parts.scale": (scale, scale, scale)})
    mesh = transform(mesh, job.parts)
    _check_stack(_sliced(mesh, job), job, (0.1, 0.4, 0.7))


def test_demo_mug_overhang_mode_and_hook_wall():
    from icefab.demo import demo_mug
    from icefab.types import Stack
    from test_regions import check_overhang_invariants

    job = Job().replace(**{"slicing.layer_thickness_mm": 0.25, "cell.cpus": 1,
                           "scaffold.mode": "overhang", "scaffold.overhang_angle_deg": 45.0,
                           "scaffold.min_width_mm": 0.0})
    stack = _sliced(demo_mug(), job)
    # the handle: 40 layers around the lower arc
    arc = Stack(stack.layers[102:142], job, stack.layer_thickness)
    scaffolded = add_scaffold(arc, job)
    check_overhang_invariants(scaffolded, 45.0)
    assert 0 < scaffolded.layers[0].scaffold.area
    surround = add_scaffold(arc, job.replace(**{"scaffold.mode": "surround"}))
    assert scaffolded.layers[0].scaffold.area < 0.5 * surround.layers[0].scaffold.area
    # hook wall on the first 40 layers: the outline never steps outward going up
    hook = job.replace(**{"scaffold.hook_wall": True})
    base = add_scaffold(Stack(stack.layers[:40], hook, stack.layer_thickness), hook)
    check_overhang_invariants(base, 0.0)
    for k in (0, 12):
        layer = base.layers[k]
        lp = plan_layer(layer, hook)
        check_layer_paths(layer, lp, hook, min_cover=0.8, hook=True)
