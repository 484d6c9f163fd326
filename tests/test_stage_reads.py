"""Each stage reads only its own settings and earlier stages' (issue 12): every stage of the
pipeline is run on the demo mug with a Job that records which settings are read, and each
read setting must belong (``icefab.stages.READS``, the one declaration) to that stage or an
earlier one. A stage reading a later stage's setting would make that later setting
invalidate an earlier result unnoticed by every cache and re-plan built on READS."""
from __future__ import annotations

import dataclasses

import pytest

from icefab import stages
from icefab.config import job_from_dict
from icefab.core import BuildMotion, Stack
from icefab.demo import demo_mug
from icefab.flow import plan_valves
from icefab.mesh import transform
from icefab.motion import plan_toolpaths
from icefab.paths import plan_paths
from icefab.regions import add_scaffold
from icefab.sim import simulate_build
from icefab.slicing import slice_mesh


class Recorder:
    """A read-only view of a Job (or one of its sections) that records the dotted name of
    every setting read through it."""

    def __init__(self, obj, prefix: str, seen: set[str]) -> None:
        object.__setattr__(self, "_obj", obj)
        object.__setattr__(self, "_prefix", prefix)
        object.__setattr__(self, "_seen", seen)

    def _wrap(self, name: str, value):
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            return Recorder(value, f"{self._prefix}{name}.", self._seen)
        self._seen.add(self._prefix + name)
        return value

    def __getattr__(self, name: str):
        value = getattr(self._obj, name)
        if callable(value) and not dataclasses.is_dataclass(value):
            return value  # methods (Materials.__getitem__ helpers, Job.replace)
        return self._wrap(name, value)

    def __getitem__(self, key: str):
        return self._wrap(key, self._obj[key])

    def __setattr__(self, name, value):  # pragma: no cover - stages never write a job
        raise AttributeError("the job is read-only")


def _late(seen: set[str], step: str) -> list[str]:
    """Settings read by ``step`` that belong to a later step."""
    at = stages.STEPS.index(step)
    early = stages.CHECKED_EARLY.get(step, ())
    return sorted(s for s in seen if s not in stages.NEUTRAL and s not in early
                  and stages.STEPS.index(stages.step_of(s)) > at)


@pytest.fixture(scope="module")
def pipeline():
    job = job_from_dict({"cell": {"cpus": 1}, "simulation": {"deposition": "valves"}})
    reads: dict[str, set[str]] = {}

    def spy(step: str) -> Recorder:
        reads[step] = set()
        return Recorder(job, "", reads[step])

    stack = slice_mesh(transform(demo_mug(), job.parts), spy("slice"))
    stack = Stack(layers=stack.layers[:8], job=job, layer_thickness=stack.layer_thickness)
    stack = add_scaffold(stack, spy("scaffold"))
    tp = plan_paths(stack, spy("paths"))
    motion = plan_toolpaths(dataclasses.replace(tp, job=job), spy("motion"))
    rec = spy("valves")
    for lm in motion.layers:
        for t in lm.trajectories:
            if t.path is not None and t.path.depositing:
                plan_valves(t, t.path.material, rec)
    sim_job = spy("simulate")
    simulate_build(BuildMotion(layers=motion.layers, job=sim_job, robot=motion.robot,
                               joint_names=motion.joint_names), sim_job)
    return reads


@pytest.mark.parametrize("step", stages.STEPS)
def test_a_stage_reads_no_later_stages_settings(pipeline, step):
    seen = pipeline[step]
    assert seen, f"{step}: recorded no setting at all (the recorder does not see the job)"
    assert not _late(seen, step), (step, _late(seen, step))


def test_every_read_setting_is_declared(pipeline):
    for step, seen in pipeline.items():
        for name in seen:
            stages.step_of(name)  # KeyError names an undeclared setting


def test_the_recorder_catches_a_late_read():
    """The check can fail: slicing that read a motion setting would be reported."""
    seen = {"slicing.layer_thickness_mm", "motion.dt_s"}
    assert _late(seen, "slice") == ["motion.dt_s"]
