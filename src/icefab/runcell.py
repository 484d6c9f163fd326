"""The cell as the build runner sees it: a small interface, and an in-process model cell.

:class:`Cell` is everything :mod:`icefab.build` asks of a cell (thesis 2.5, Fig. 2-5):
a handshake, the cell's state (which sequence number it completed last, which path a
fault cut short), one path at a time (its trajectory and, for deposition, its valve
program; the cell uploads and verifies the program, triggers, runs the motion and
reports the path done), the end of a layer, the laser samples of a measurement path,
and a stop (valves off first, robot to a safe point).

Sequence numbers make every command idempotent: a cell remembers the highest ``seq`` it
completed (paths run in ``seq`` order) and answers a command with ``seq`` at or below
it with "already done" instead of running it again. So after a crash of the control PC
the runner re-sends what its journal does not show as done, with the old numbers, and
every path is deposited exactly once.

``icefab build`` runs on :class:`icefab.linkedcell.LinkedCell`: this interface on
the three links of a real cell or of ``icefab cell serve`` (issue 13). :class:`VirtualCell`
here is a model cell in the runner's own process, for the runner's tests that inject a
crash at any command: it keeps its state in a folder (``state.npz``, written atomically
and fsync'ed after every path, and ``surface.npz``: ``origin`` (2,) mm, ``spacing`` mm,
``z`` (ny, nx) mm heights from the platform, NaN where nothing was deposited; rewritten
at every layer end), so it survives being opened again as real ice would. It deposits
with :mod:`icefab.sim`'s kernels: every valve pulse drops the volume its valve's
calibration table gives at the pulse's local frequency (from the pulse intervals: the
virtual valve only sees pulse instants, like the real one), times the simulated flow
error and drift, along the nozzle's trajectory (:func:`icefab.sim.pulse_segments`); at a
layer's end the liquid levels, the edges lose some and height noise is added, drawn
from ``(simulation.seed, layer)`` so that the same commands give the same surface
whatever the timing or the interruptions. The laser reads the frozen surface at 100 Hz
along measurement paths with the simulated latency (``simulation.laser_latency_s``) and
noise drawn from ``(seed, layer, item)``; samples are tagged with the end-effector
position (robot base frame) at their instant, as the real cell reports them.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from icefab.errors import CellError

log = logging.getLogger(__name__)

STATE_FILE = "state.npz"
SURFACE_FILE = "surface.npz"
JOB_FILE = "job.toml"
LASER_DIR = "laser"


@dataclass(frozen=True, eq=False)
class CellPath:
    """One path as sent to the cell.

    layer: toolpaths layer index; item: the trajectory's index in the layer; role:
    boundary / fill / measure / travel; tool: part / scaffold (deposition), laser, none.
    xy: (n, 2) float64 mm, end-effector positions in the robot base frame every dt_s s.
    z_mm: nominal top of the layer, mm. width_mm: deposition width (0 otherwise).
    program: the valve program's bytes (:func:`icefab.flow.encode_valve_program`) for a
    deposition path, else empty.
    """

    layer: int
    item: int
    role: str
    tool: str
    xy: np.ndarray
    dt_s: float
    z_mm: float
    width_mm: float
    program: bytes = b""

    def digest(self) -> str:
        from icefab.journal import digest_bytes

        head = f"{self.layer}|{self.item}|{self.role}|{self.tool}|{self.dt_s!r}|" \
               f"{self.z_mm!r}|{self.width_mm!r}|".encode()
        return digest_bytes(head + np.ascontiguousarray(self.xy, np.float64).tobytes()
                            + self.program)

    @property
    def duration_s(self) -> float:
        return max(len(self.xy) - 1, 0) * self.dt_s


@dataclass(frozen=True)
class CellStatus:
    """last_done: highest seq completed (0: none); cut: seq of a path a fault cut short
    (0: none); grid: whether the cell holds a build (prepared)."""

    last_done: int
    cut: int
    prepared: bool


class Cell(Protocol):
    """What the build runner needs from a cell (see the module docstring)."""

    def hello(self) -> dict: ...

    def status(self) -> CellStatus: ...

    def prepare(self, job_toml: str, lo_mm: tuple[float, float],
                hi_mm: tuple[float, float]) -> None: ...

    def run_path(self, seq: int, path: CellPath,
                 upcoming: tuple[int, CellPath] | None = None) -> bool:
        """Run one path (False: ``seq`` was done already). ``upcoming``: the next path
        (its journal number and CellPath), which the cell may upload while this one runs
        so that the robot never waits for data; it is run by the next call."""
        ...

    def end_layer(self, seq: int, layer: int) -> bool: ...

    def laser_samples(self, seq: int, path: CellPath) -> np.ndarray: ...

    def stop(self) -> float | None:
        """Valves off first, then the robot stops and retracts to a safe point above the
        part (a motion that does not count as a path done). Returns how far it lifted the
        tool, mm (0: not lifted), or None when the cell does not say."""
        ...

    def close(self) -> None:
        """Close the links (the cell itself carries on)."""
        ...


# =========================================================================== the virtual cell


def _fsync_write_npz(path: Path, **arrays: Any) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    dfd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)


class VirtualCell:
    """A model cell whose state lives in ``state_dir`` (see the module docstring). A path
    runs within one call, so it is never cut short here: tests that need a cut say so
    through :meth:`status`."""

    def __init__(self, state_dir: str | os.PathLike) -> None:
        self.dir = Path(state_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        (self.dir / LASER_DIR).mkdir(exist_ok=True)
        self._job = None
        self._st: dict[str, np.ndarray] | None = None
        f = self.dir / STATE_FILE
        if f.is_file():
            with np.load(f) as z:
                self._st = {k: z[k] for k in z.files}

    # ------------------------------------------------------------------ helpers

    @property
    def job(self):
        if self._job is None:
            from icefab.config import load_job

            self._job = load_job(self.dir / JOB_FILE, stored=True)
        return self._job

    def _save(self) -> None:
        _fsync_write_npz(self.dir / STATE_FILE, **self._st)

    def _need(self) -> dict[str, np.ndarray]:
        if self._st is None:
            raise CellError("the virtual cell holds no build: prepare it first")
        return self._st

    # ------------------------------------------------------------------ Cell

    def hello(self) -> dict:
        return {"cell": "icefab virtual cell", "version": 1, "pid": os.getpid()}

    def status(self) -> CellStatus:
        st = self._st
        if st is None:
            return CellStatus(0, 0, False)
        return CellStatus(int(st["last_done"]), int(st["cut"]), True)

    def prepare(self, job_toml: str, lo_mm, hi_mm) -> None:
        """Start a build: the job (the cell's physics: calibration tables, frames,
        disturbances) and the box the part and scaffold occupy (part frame, mm)."""
        from icefab.sim import empty_surface

        if self._st is not None:
            raise CellError("the virtual cell holds a build already")
        (self.dir / JOB_FILE).write_text(job_toml, encoding="utf-8")
        self._job = None
        job = self.job
        wmax = max(job.materials.part.fill_width_mm, job.materials.scaffold.fill_width_mm,
                   job.materials.part.path_width_mm, job.materials.scaffold.path_width_mm)
        g = job.simulation.grid_mm
        surf = empty_surface(np.asarray(lo_mm), np.asarray(hi_mm), g, 2 * wmax + 2 * g)
        ny, nx = surf.z.shape
        self._st = {"origin": surf.origin, "spacing": np.float64(g), "z": surf.z,
                    "layer_img": np.zeros((2, ny, nx)), "ever": np.zeros((ny, nx), bool),
                    "used_cm3": np.zeros(2), "last_done": np.int64(0),
                    "cut": np.int64(0), "layers": np.int64(0)}
        self._save()

    def run_path(self, seq: int, path: CellPath, upcoming=None) -> bool:
        """Run one path; False (nothing done) when ``seq`` was completed already
        (``upcoming``: not used, nothing here takes time to upload)."""
        st = self._need()
        if seq <= int(st["last_done"]):
            return False
        if path.tool in ("part", "scaffold") and path.program:
            self._deposit(path, self._drops(path))
        elif path.role == "measure":
            self._measure(seq, path)
        st["last_done"] = np.int64(seq)
        self._save()
        self._executed(seq)
        return True

    def _executed(self, seq: int) -> None:
        """Append ``seq`` to ``executed.log``: what the cell really ran, once per line
        (the exactly-once evidence the tests and the benchmark read)."""
        with open(self.dir / "executed.log", "a", encoding="utf-8") as f:
            f.write(f"{seq}\n")
            f.flush()
            os.fsync(f.fileno())

    def end_layer(self, seq: int, layer: int) -> bool:
        """Freeze the layer's deposit: the liquid levels, edges lose, noise is added."""
        from icefab import sim as simmod

        st = self._need()
        if seq <= int(st["last_done"]):
            return False
        job = self.job
        s = job.simulation
        dh = job.slicing.layer_thickness_mm
        g = float(st["spacing"])
        img = st["layer_img"]
        z = st["z"]
        if s.edge_loss > 0:
            w = max(job.materials.part.path_width_mm, job.materials.scaffold.path_width_mm)
            img = img * simmod._edge_factor(img[0] + img[1], 0.25 * dh, w, g, s.edge_loss)
        added = img[0] + img[1]
        mask = added > 0.25 * dh
        if s.spread_mm > 0:
            added = simmod.level_liquid(z, added, g, s.spread_mm)
            mask |= added > 0.25 * dh
        if s.noise_mm > 0 and mask.any():
            rng = np.random.default_rng([s.seed, 1, int(layer)])
            added = added + s.noise_mm * mask * simmod._noise_field(rng, z.shape,
                                                                    s.noise_corr_mm / g)
        st["z"] = z + added
        st["ever"] = st["ever"] | mask
        st["layer_img"] = np.zeros_like(img)
        st["layers"] = np.int64(int(st["layers"]) + 1)
        st["last_done"] = np.int64(seq)
        _fsync_write_npz(self.dir / SURFACE_FILE, origin=st["origin"],
                         spacing=st["spacing"], z=np.where(st["ever"], st["z"], np.nan))
        self._save()
        self._executed(seq)
        return True

    def laser_samples(self, seq: int, path: CellPath) -> np.ndarray:
        """(m, 4) float64: t s from the path start, EE x, y (base frame, mm), z reading mm
        of the measurement path with this ``seq``."""
        f = self.dir / LASER_DIR / f"{seq:08d}.npy"
        if not f.is_file():
            raise CellError(f"no laser samples for path {seq}")
        return np.load(f)

    def stop(self) -> None:
        """Valves off, robot to its safe point: the model cell runs nothing between
        commands, so there is nothing to stop."""
        return None

    def close(self) -> None:
        """Nothing to close: the model cell is this object."""
        return None

    # ------------------------------------------------------------------ physics

    def _drops(self, path: CellPath):
        """Segments of a deposition path's pulses: (a, b, volume, half width, n0, n1,
        ext) from :func:`icefab.sim.pulse_segments`, volumes as the valve drops them."""
        from icefab import flow
        from icefab import sim as simmod

        job = self.job
        prog = flow.decode_valve_program(path.program, f"path {path.layer}/{path.item}")
        t = flow.pulse_times(prog)
        cal = flow.calibration_for(path.tool, job)
        if len(t) == 0:
            drops = np.zeros(0)
        elif prog.widths_us is None:
            # the local frequency: the inverse of the mean interval to the neighbours
            if len(t) == 1:
                period = np.array([max(prog.duration, job.flow.tick_s)])
            else:
                d = np.diff(t)
                left = np.concatenate([d[:1], d])
                right = np.concatenate([d, d[-1:]])
                period = np.maximum(0.5 * (left + right), job.flow.tick_s)
            nu = 1.0 / period
            drops = cal.flow(nu) / nu
        else:
            f = job.flow.pwm_frequency_hz
            per = float(cal.flow(np.array([f]))[0]) / f
            w = np.concatenate([pc.widths_us for pc in flow.program_pieces(prog)])
            drops = per * w.astype(np.float64) / 1000.0 / job.flow.calibration_pulse_ms
        off = np.asarray(job.cell.ee_origin_mm) - _tool_offset(path.tool, job)
        xy = np.asarray(path.xy, dtype=np.float64) - off
        a, b, vol, hw, owner, n0, n1, ext = simmod.pulse_segments(
            [xy], [path.dt_s], [t], [drops], [path.width_mm])
        return a, b, vol, hw, n0, n1, ext

    def _deposit(self, path: CellPath, seg) -> None:
        from icefab import sim as simmod

        st = self._st
        job = self.job
        s = job.simulation
        a, b, vol, hw, n0, n1, ext = seg
        if len(vol) == 0:
            return
        mat = 0 if path.tool == "part" else 1
        before = st["used_cm3"][mat] + (np.cumsum(vol) - vol) / 1000.0
        gain = simmod.cell.flow_gain(s, before)
        st["used_cm3"][mat] += vol.sum() / 1000.0
        simmod._splat(st["layer_img"][mat], st["origin"], float(st["spacing"]), a, b,
                      vol * gain, hw, n0, n1, ext)

    def _measure(self, seq: int, path: CellPath) -> None:
        from icefab.sim import sample_surface
        from icefab.core import HeightMap

        st = self._st
        job = self.job
        s = job.simulation
        xy = np.asarray(path.xy, dtype=np.float64)
        if len(xy) < 2:
            out = np.zeros((0, 4))
        else:
            tt = np.arange(len(xy)) * path.dt_s
            tk = np.arange(int(np.floor(tt[-1] * s.laser_rate_hz + 1e-9)) + 1) / s.laser_rate_hz

            def at(q: np.ndarray) -> np.ndarray:
                return np.column_stack([np.interp(q, tt, xy[:, 0]), np.interp(q, tt, xy[:, 1])])

            ee = at(tk)
            spot = at(np.maximum(tk - s.laser_latency_s, 0.0)) \
                - np.asarray(job.cell.ee_origin_mm) + np.asarray(job.cell.laser_offset_mm)
            surf = HeightMap(origin=st["origin"], spacing=float(st["spacing"]), z=st["z"])
            zr = sample_surface(surf, spot)
            if s.laser_noise_mm > 0:
                rng = np.random.default_rng([s.seed, 3, path.layer, path.item])
                zr = zr + rng.normal(0.0, s.laser_noise_mm, len(zr))
            out = np.column_stack([tk, ee, zr])
        f = self.dir / LASER_DIR / f"{seq:08d}.npy"
        tmp = f.with_name(f".{f.name}.tmp")
        with open(tmp, "wb") as fh:
            np.save(fh, out)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, f)


def _tool_offset(tool: str, job) -> np.ndarray:
    from icefab.frames import tool_offset

    return np.asarray(tool_offset(tool, job), dtype=np.float64)
