"""The three links of a cell opened together, and one layer run through them (thesis 2.3,
Fig. 2-5: the control PC sends data, the C40 gives the real-time signals).

The reference client of the links, used by the end-to-end test and benchmark and
available to a build runner::

    links = CellLinks.open(read_endpoints("state"))      # or real devices
    run = run_layer(links, layer_motion, job)              # LayerRun: laser samples, pulses
    links.close()

Per path of the layer, in order: the robot path is uploaded (:class:`RobotLink`); a
deposition path's valve program is uploaded, verified and armed on the valve controller
and the robot's ``GO`` is the trigger (:meth:`ValveController.play` with the robot as its
trigger, so the play starts when the C40 raises its output); a measurement path clears
and starts the laser's storage before ``GO`` and reads it out after ``DN``; travel just
moves. ``LB`` / ``LE`` bracket the layer.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from icefab.cell import robot_protocol as rp
from icefab.cell.laser import LaserLink, path_samples
from icefab.cell.robot import RobotLink, robot_paths

log = logging.getLogger(__name__)

__all__ = ["CellLinks", "LayerRun", "run_layer"]


@dataclass
class CellLinks:
    """Open links to the robot controller, the valve controller and the laser."""

    robot: RobotLink
    valves: object          # icefab.cell.valve.ValveController
    laser: LaserLink

    @classmethod
    def open(cls, endpoints: dict, *, timeout_s: float = 10.0) -> "CellLinks":
        """From an endpoints dict (``DIR/endpoints.json`` of ``icefab cell serve``, or the
        same keys for real devices); says hello on every link. CellError / ValveLinkError
        naming the device that does not answer."""
        from icefab.cell.valve import ValveController

        robot = RobotLink.connect(endpoints["robot"]["host"], endpoints["robot"]["port"],
                                  timeout_s=timeout_s)
        try:
            robot.hello()
            valves = ValveController.open(endpoints["valve"]["device"])   # says HELLO
            try:
                laser = LaserLink.open(endpoints["laser"]["device"], timeout_s=timeout_s)
            except BaseException:
                valves.close()
                raise
        except BaseException:
            robot.close()
            raise
        return cls(robot, valves, laser)

    def close(self) -> None:
        self.laser.close()
        self.valves.close()
        self.robot.close()

    def __enter__(self) -> "CellLinks":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass(frozen=True)
class LayerRun:
    """What one layer gave back: ``samples`` (k, 3) float64 mm, the laser samples of its
    measurement paths in the part frame (thesis 5.2.1); ``pulses`` emitted per valve;
    ``paths`` run; ``seqs`` their robot sequence numbers in order."""

    samples: np.ndarray
    pulses: tuple[int, int]
    paths: int
    seqs: tuple[int, ...]


def run_layer(links: CellLinks, layer, job, *, action=None, timeout_s: float = 60.0
              ) -> LayerRun:
    """Run one ``icefab.motion.LayerMotion`` through the links (see the module doc).

    The valve programs are planned here (:func:`icefab.flow.replan_valves`, with the
    control ``action`` if given: nu-controller flow x (1 + u), or c-controller re-timed
    trajectories, which the robot then runs). Returns a :class:`LayerRun`.
    """
    from icefab import flow
    from icefab.cell.valve import VALVES

    dep = [t for t in layer.trajectories
           if len(t.xy) and t.path is not None and t.path.depositing]
    trajs, progs = flow.replan_valves(dep, job, action=action) if dep else ((), ())
    timed = dict(zip(map(id, dep), zip(trajs, progs)))
    run_trajs = tuple(timed[id(t)][0] if id(t) in timed else t for t in layer.trajectories)
    program_of = {k: timed[id(t)][1] for k, t in enumerate(layer.trajectories)
                  if id(t) in timed}
    import dataclasses

    paths = robot_paths(dataclasses.replace(layer, trajectories=run_trajs), job)
    samples, seqs = [], []
    pulses = [0, 0]
    links.robot.begin_layer(layer.index, float(layer.z))
    for p in paths:
        seq = links.robot.upload(p)
        seqs.append(seq)
        wait = timeout_s + p.duration_s
        if p.flags & rp.FLAG_VALVE:
            valve = VALVES[p.tool]
            report = links.valves.play({valve: program_of[p.index]},
                                       trigger=lambda: links.robot.go(seq))
            pulses[0] += int(report.emitted[0])
            pulses[1] += int(report.emitted[1])
            links.robot.wait_done(seq, wait)
        elif p.flags & rp.FLAG_LASER:
            links.laser.clear()
            links.laser.start()
            links.robot.go(seq)
            links.robot.wait_done(seq, wait)
            links.laser.stop()
            samples.append(path_samples(p, links.laser.read_stored(), job))
        else:
            links.robot.go(seq)
            links.robot.wait_done(seq, wait)
    links.robot.end_layer(layer.index)
    return LayerRun(samples=np.concatenate(samples) if samples else np.zeros((0, 3)),
                    pulses=(pulses[0], pulses[1]), paths=len(paths), seqs=tuple(seqs))
