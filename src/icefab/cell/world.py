"""The physical side of the virtual cell: the part's surface, what valves and laser do to
and read from it, and its state on disk (``DIR/surface.npz``).

The model is :mod:`icefab.sim`'s, valve-pulse deposition (``simulation.deposition =
"valves"``), applied as the cell runs: each deposition path leaves its pulses' drops in
the current layer's liquid (:func:`icefab.sim.pulse_segments`); the layer freezes
(:meth:`World.freeze`) when its first measurement path starts or the robot ends the layer
(``LE``): flow gain with drift, edge loss, liquid levelling, height noise and debris, then
added to the frozen surface -- the steps and the order of :func:`icefab.sim.run_cell`'s
layer loop. Laser paths read the frozen surface (latency, noise) at the storage rate.

Determinism: the random numbers come from generators seeded by ``simulation.seed``
(height noise ``[seed, 1]``, debris ``[seed, 2]``, laser ``[seed, 3]``, as in
``run_cell``) whose states are saved with the surface after every path, so the same
sequence of paths gives a bit-identical surface whatever the timing and across restarts.

The valve model: a pulse of valve ``v`` (0 part, 1 scaffold) with width ``w`` drops, in
PWM mode, ``Q(f) / f * w / calibration_pulse_ms`` at the PWM frequency ``f`` (as
:func:`icefab.sim.pulse_drops`); in FM mode ``Q(nu) / nu`` at the rate ``nu`` the valve is
actually pulsing at (the inverse of the mean of the intervals to its neighbouring pulses),
where the simulator uses the commanded frequency the cell cannot know. The drops land
along the path the robot ran, in the part frame under the valve's nozzle, with the path's
width.

``surface.npz`` layout (format "icefab-cell-surface", version 1), all lengths in mm:

* ``origin`` (2,) float64: x, y of grid node [0, 0] (part frame); ``spacing`` float64;
  ``z`` (ny, nx) float64: frozen height above the platform at node (iy, ix) = point
  ``origin + (ix, iy) * spacing``; ``ever`` (ny, nx) bool: ever deposited on;
* ``layers_frozen`` int64, ``used_cm3`` (2,) float64 (volume through each valve, drift);
* ``last_done``, ``cut`` int64: the robot's sequence numbers of the last path run to its
  end and of the last path stopped mid-motion (0: none), saved with the deposit they
  describe so that a restarted cell reports what its surface holds (absent in files
  written before them: 0);
* ``rng_noise``, ``rng_debris``, ``rng_laser``: JSON of the generators' states;
* ``job``: TOML of the job the cell runs with;
* the current layer's liquid not frozen yet: ``pend_*`` arrays (segments of its drops:
  ``pend_a``, ``pend_b`` (m, 2), ``pend_vol``, ``pend_hw``, ``pend_ext`` (m,),
  ``pend_mat`` (m,) int8, ``pend_n0``, ``pend_n1`` (m, 2); ``pend_mid`` (k, 2) the
  midpoints of the layer's commanded path chords, where debris falls), ``pend_layer``;
* ``generation`` int64 (absent in older files: 0), see below.

A path that leaves the frozen surface as it was (a deposition path adds liquid, a laser
path over an already frozen layer draws laser noise) is saved as a *liquid piece*,
``liquid-<generation>-<k>.npz`` beside ``surface.npz``: the ``pend_*`` rows added since the
last save, ``pend_layer``, ``last_done``, ``cut`` and ``rng_laser``. A state is
``surface.npz`` and its generation's pieces in ``k`` order. Only a save after the surface
changed (a freeze) writes ``surface.npz`` whole, with the next generation, and then
deletes the older pieces (a crash in between leaves pieces of an older generation, which
a read ignores and removes). Rewriting the whole surface and the layer's liquid after
every path wrote ~5 MB a path on a 300 mm part and grew with the paths of the layer
(BENCHMARKS.md, "The virtual cell's surface saved by pieces").
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from icefab import sim as _simulator  # the layer step and blocks shared with run_cell
from icefab.errors import CellError
from icefab.resultfiles import NPZ_DAMAGE

log = logging.getLogger(__name__)

FORMAT = "icefab-cell-surface"
VERSION = 1
_TINY_MM = 1e-9
MATERIAL_OF_VALVE = ("part", "scaffold")


@dataclass
class Pending:
    """The current layer's liquid: drop segments (commanded volumes) and chord midpoints."""

    layer: int = -1
    a: list = field(default_factory=list)
    b: list = field(default_factory=list)
    vol: list = field(default_factory=list)
    hw: list = field(default_factory=list)
    mat: list = field(default_factory=list)
    n0: list = field(default_factory=list)
    n1: list = field(default_factory=list)
    ext: list = field(default_factory=list)
    mid: list = field(default_factory=list)

    def empty(self) -> bool:
        return not self.mid and not self.a

    def marks(self) -> tuple[int, int]:
        """How many drop-segment blocks and chord-midpoint blocks the liquid holds (where
        :meth:`arrays` starts the rows added after this moment)."""
        return len(self.a), len(self.mid)

    def arrays(self, since: tuple[int, int] = (0, 0)) -> dict:
        """The ``pend_*`` arrays of surface.npz; ``since`` (from :meth:`marks`): only the
        rows added after that moment."""
        s, m = since

        def cat(parts, shape, dtype=np.float64):
            return np.concatenate(parts).astype(dtype) if parts else np.zeros(shape, dtype)
        return {"pend_layer": np.int64(self.layer),
                "pend_a": cat(self.a[s:], (0, 2)), "pend_b": cat(self.b[s:], (0, 2)),
                "pend_vol": cat(self.vol[s:], (0,)), "pend_hw": cat(self.hw[s:], (0,)),
                "pend_mat": cat(self.mat[s:], (0,), np.int8),
                "pend_n0": cat(self.n0[s:], (0, 2)), "pend_n1": cat(self.n1[s:], (0, 2)),
                "pend_ext": cat(self.ext[s:], (0,)), "pend_mid": cat(self.mid[m:], (0, 2))}

    def extend(self, d) -> None:
        """Append the ``pend_*`` rows of a saved state (an npz) to the liquid."""
        self.layer = int(d["pend_layer"])
        if len(d["pend_a"]):
            self.a.append(d["pend_a"].copy())
            self.b.append(d["pend_b"].copy())
            self.vol.append(d["pend_vol"].copy())
            self.hw.append(d["pend_hw"].copy())
            self.mat.append(d["pend_mat"].copy())
            self.n0.append(d["pend_n0"].copy())
            self.n1.append(d["pend_n1"].copy())
            self.ext.append(d["pend_ext"].copy())
        if len(d["pend_mid"]):
            self.mid.append(d["pend_mid"].copy())


def pulse_rate_drops(t: np.ndarray, material: str, job) -> np.ndarray:
    """FM drop volumes, mm^3, of pulses at instants ``t`` (s, non-decreasing) of one valve
    along one path: ``Q(nu) / nu`` with ``nu`` the rate the valve pulses at (1 / mean of
    the intervals to the neighbouring pulses; one pulse alone: the table's lowest non-zero
    frequency), clamped to the table."""
    from icefab import flow

    cal = flow.calibration_for(material, job)
    pos = cal.frequency_hz[cal.frequency_hz > 0]
    lo, hi = float(pos[0]), float(cal.frequency_hz[-1])
    n = len(t)
    if n == 0:
        return np.zeros(0)
    if n == 1:
        nu = np.array([lo])
    else:
        d = np.diff(t)
        left = np.concatenate([d[:1], d])
        right = np.concatenate([d, d[-1:]])
        mean = 0.5 * (left + right)
        nu = np.divide(1.0, mean, out=np.full(n, hi), where=mean > 0)
    nu = np.clip(nu, lo, hi)
    return cal.flow(nu) / nu


class World:
    """The virtual cell's surface and its state folder. See the module docstring."""

    def __init__(self, state_dir: str | os.PathLike, job, *, origin=None, shape=None,
                 spacing: float | None = None):
        self.dir = Path(state_dir)
        self.job = job
        self.file = self.dir / "surface.npz"
        self.pending = Pending()
        self.generation = 0
        self._pieces = 0            # liquid pieces of this generation on disk
        self._saved = (0, 0)        # the liquid's marks at the last save
        self._surface_changed = True
        if self.file.exists():
            self._load()
        else:
            if origin is None or shape is None:
                raise CellError(f"{self.file}: no surface yet; give the grid (--grid-for "
                                "TRAJECTORIES or --bounds) to start a new one")
            # a new part: no piece left in the folder is its liquid (every new surface
            # starts again at generation 1, and took over an old part's pieces: a tester's
            # fresh cell reported 3 paths done and 388 segments it never deposited)
            self._remove_pieces(keep=None)
            sim = job.simulation
            self.origin = np.asarray(origin, dtype=np.float64)
            self.spacing = float(spacing if spacing is not None else sim.grid_mm)
            self.z = np.zeros(tuple(int(v) for v in shape))
            self.ever = np.zeros(self.z.shape, dtype=bool)
            self.layers_frozen = 0
            self.last_done = 0
            self.cut = 0
            self.used_cm3 = np.zeros(2)
            self.rng_noise = np.random.default_rng([sim.seed, 1])
            self.rng_debris = np.random.default_rng([sim.seed, 2])
            self.rng_laser = np.random.default_rng([sim.seed, 3])
            self.save()

    # ------------------------------------------------------------------ state on disk

    def save(self) -> None:
        """Save the state atomically (a crash leaves the previous one): ``surface.npz``
        whole after the surface changed, else a liquid piece (module docstring)."""
        from icefab.atomic import atomic_path
        from icefab.config import to_toml

        self.dir.mkdir(parents=True, exist_ok=True)
        if not self._surface_changed:
            data = {"last_done": np.int64(self.last_done), "cut": np.int64(self.cut),
                    "rng_laser": np.array(json.dumps(self.rng_laser.bit_generator.state)),
                    **self.pending.arrays(self._saved)}
            with atomic_path(self._piece_file(self.generation, self._pieces),
                             suffix=".npz") as tmp, open(tmp, "wb") as fh:
                np.savez(fh, **data)
            self._pieces += 1
            self._saved = self.pending.marks()
            return
        data = {"format": np.array(FORMAT), "version": np.array(VERSION),
                "generation": np.int64(self.generation + 1),
                "origin": self.origin, "spacing": np.float64(self.spacing), "z": self.z,
                "ever": self.ever, "layers_frozen": np.int64(self.layers_frozen),
                "last_done": np.int64(self.last_done), "cut": np.int64(self.cut),
                "used_cm3": self.used_cm3,
                "rng_noise": np.array(json.dumps(self.rng_noise.bit_generator.state)),
                "rng_debris": np.array(json.dumps(self.rng_debris.bit_generator.state)),
                "rng_laser": np.array(json.dumps(self.rng_laser.bit_generator.state)),
                "job": np.array(to_toml(self.job)), **self.pending.arrays()}
        with atomic_path(self.file, suffix=".npz") as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **data)
        self.generation += 1
        self._pieces = 0
        self._saved = self.pending.marks()
        self._surface_changed = False
        self._remove_pieces(keep=self.generation)

    def _piece_file(self, generation: int, k: int) -> Path:
        return self.dir / f"liquid-{generation}-{k}.npz"

    def _piece_files(self) -> list[tuple[int, int, Path]]:
        """(generation, k, file) of the liquid pieces in the state folder, in order."""
        found = []
        for f in self.dir.glob("liquid-*-*.npz"):
            _, gen, k = f.stem.split("-", 2)
            if gen.isdigit() and k.isdigit():
                found.append((int(gen), int(k), f))
        return sorted(found)

    def _remove_pieces(self, keep: int | None) -> None:
        """Delete the liquid pieces of other generations than ``keep`` (None: every one;
        the surface file of a later generation holds their liquid, or they are a crash's
        leftovers), and the temporary files of pieces and surfaces a killed cell left
        (hidden, older than a minute: a save in flight takes milliseconds)."""
        for gen, _, f in self._piece_files():
            if gen != keep:
                f.unlink(missing_ok=True)
        stale = time.time() - 60.0
        for f in (*self.dir.glob(".liquid-*.npz"), *self.dir.glob(".surface.npz.*")):
            try:
                if f.stat().st_mtime < stale:
                    f.unlink()
            except OSError:
                pass

    def _load(self) -> None:
        try:
            with np.load(self.file, allow_pickle=False) as d:
                if str(d["format"]) != FORMAT or int(d["version"]) != VERSION:
                    raise CellError(f"{self.file}: not an icefab cell surface (format "
                                    f"{str(d['format'])!r} version {int(d['version'])})")
                self.origin = np.asarray(d["origin"], dtype=np.float64).reshape(2)
                self.spacing = float(d["spacing"])
                self.z = np.array(d["z"], dtype=np.float64)
                self.ever = np.array(d["ever"], dtype=bool)
                self.layers_frozen = int(d["layers_frozen"])
                self.last_done = int(d["last_done"]) if "last_done" in d.files else 0
                self.cut = int(d["cut"]) if "cut" in d.files else 0
                self.used_cm3 = np.array(d["used_cm3"], dtype=np.float64).reshape(2)
                gens = []
                for key in ("rng_noise", "rng_debris", "rng_laser"):
                    g = np.random.default_rng()
                    g.bit_generator.state = json.loads(str(d[key]))
                    gens.append(g)
                self.rng_noise, self.rng_debris, self.rng_laser = gens
                self.generation = int(d["generation"]) if "generation" in d.files else 0
                self.pending = Pending()
                self.pending.extend(d)
        except CellError:
            raise
        except NPZ_DAMAGE as exc:   # a truncated piece ended the cell in a traceback
            raise CellError(f"{self.file}: cannot read the cell surface ({exc})") from None
        self._remove_pieces(keep=self.generation)
        for _, k, f in self._piece_files():
            if k != self._pieces:
                raise CellError(f"{f}: liquid piece {k} of the cell surface where piece "
                                f"{self._pieces} should be (a piece is missing)")
            try:
                with np.load(f, allow_pickle=False) as d:
                    self.pending.extend(d)
                    self.last_done, self.cut = int(d["last_done"]), int(d["cut"])
                    self.rng_laser.bit_generator.state = json.loads(str(d["rng_laser"]))
            except NPZ_DAMAGE as exc:
                raise CellError(f"{f}: cannot read a liquid piece of the cell surface "
                                f"({exc})") from None
            self._pieces += 1
        self._saved = self.pending.marks()
        self._surface_changed = False
        if self.z.ndim != 2 or self.ever.shape != self.z.shape or not self.spacing > 0 \
                or not np.isfinite(self.z).all() or not np.isfinite(self.origin).all():
            raise CellError(f"{self.file}: inconsistent surface arrays (z {self.z.shape}, "
                            f"ever {self.ever.shape}, spacing {self.spacing})")

    def height_map(self):
        """The frozen surface as a :class:`~icefab.core.HeightMap` (NaN where nothing was
        ever deposited), like ``SimResult.height``."""
        from icefab.core import HeightMap

        return HeightMap(origin=self.origin.copy(), spacing=self.spacing,
                         z=np.where(self.ever, self.z, np.nan))

    # ------------------------------------------------------------------ deposition

    def deposit_path(self, layer: int, xy_base: np.ndarray, dt_s: float, width_mm: float,
                     tool: str, pulses: list[tuple[int, float, float]]) -> int:
        """The drops of one deposition path into the layer's liquid.

        xy_base: (n, 2) mm, the joint-4 axis in the base frame every ``dt_s`` (as run);
        width_mm: the path's width; tool: "part" or "scaffold", the nozzle the path was
        planned for (its chords are where debris can fall); pulses: (valve, t s from the
        trigger, width us) in order, each drop under its valve's nozzle. Returns the
        number of pulses.
        """
        from icefab import flow
        from icefab.frames import to_part_frame

        sim = _simulator
        job = self.job
        if tool not in MATERIAL_OF_VALVE:
            raise CellError(f"a deposition path for tool {tool!r}; expected part or scaffold")
        self._layer(layer)

        def part_xy(material: str) -> np.ndarray:
            return to_part_frame(xy_base, material, job)

        by_valve: dict[int, list] = {}
        for v, t, w in pulses:
            if int(v) not in (0, 1):
                raise CellError(f"valve {v}: the cell has valves 0 (part) and 1 (scaffold)")
            by_valve.setdefault(int(v), []).append((float(t), float(w)))
        p = self.pending
        for v in sorted(by_valve):
            material = MATERIAL_OF_VALVE[v]
            t = np.array([q[0] for q in by_valve[v]], dtype=np.float64)
            if job.flow.mode == "pwm":
                f = job.flow.pwm_frequency_hz
                cal = flow.calibration_for(material, job)
                per_pulse = float(cal.flow(np.array([f]))[0]) / f
                widths_ms = np.array([q[1] for q in by_valve[v]], dtype=np.float64) / 1000.0
                drops = per_pulse * widths_ms / job.flow.calibration_pulse_ms
            else:
                drops = pulse_rate_drops(t, material, job)
            a, b, vol, hw, _, n0, n1, ext = sim.pulse_segments(
                [part_xy(material)], [float(dt_s)], [t], [drops], [float(width_mm)])
            p.a.append(a)
            p.b.append(b)
            p.vol.append(vol)
            p.hw.append(hw)
            p.mat.append(np.full(len(a), v, dtype=np.int8))
            p.n0.append(n0)
            p.n1.append(n1)
            p.ext.append(ext)
        p.mid.append(_chord_midpoints(part_xy(tool)))
        return len(pulses)

    def covers(self, xy_base: np.ndarray, tool: str) -> bool:
        """Whether every point of a path, the joint-4 axis in the base frame (mm), puts
        ``tool`` ("part", "scaffold" or "laser") over the surface grid."""
        from icefab.frames import to_part_frame

        if len(xy_base) == 0:
            return True
        xy = to_part_frame(xy_base, tool, self.job)
        ny, nx = self.z.shape
        hi = self.origin + self.spacing * np.array([nx - 1, ny - 1], dtype=np.float64)
        eps = 1e-6 + 1e-9 * float(np.abs(hi).max())
        return bool((xy >= self.origin - eps).all() and (xy <= hi + eps).all())

    def _layer(self, layer: int) -> None:
        """Paths of a new layer freeze the previous one's liquid first."""
        if self.pending.layer != layer:
            if not self.pending.empty():
                self.freeze()
            self.pending.layer = int(layer)

    def freeze(self) -> bool:
        """The current layer's liquid levels and freezes onto the surface: the simulator's
        own layer step (:func:`icefab.sim.deposit_layer`, as :func:`icefab.sim.run_cell`
        takes it for valve pulses). Returns whether there was anything to freeze."""
        sim_mod = _simulator
        p = self.pending
        if p.empty():
            return False
        job = self.job
        dh = job.slicing.layer_thickness_mm
        arr = p.arrays()
        a, b, v_all, hw = arr["pend_a"], arr["pend_b"], arr["pend_vol"], arr["pend_hw"]
        mat_of, n0, n1, ext = arr["pend_mat"], arr["pend_n0"], arr["pend_n1"], arr["pend_ext"]
        mid = arr["pend_mid"]
        z = self.z
        _img, added, mask, _cover = sim_mod.deposit_layer(
            z, self.origin, self.spacing, (a, b, v_all, hw, mat_of, n0, n1, ext),
            self.used_cm3, mid, job, dh, self.rng_noise, self.rng_debris)
        z += added
        self.ever |= mask
        self.layers_frozen += 1
        self.pending = Pending(layer=p.layer)
        self._surface_changed = True
        return True

    # ------------------------------------------------------------------ laser

    def laser_values(self, xy_base: np.ndarray, dt_s: float, z_ref_mm: float) -> np.ndarray:
        """What the laser head reads along one measurement path, one value per storage
        cycle from the trigger (``simulation.laser_rate_hz``): the frozen surface height
        where the spot was ``simulation.laser_latency_s`` earlier, plus Gaussian noise
        (``laser_noise_mm``), relative to ``z_ref_mm`` (the laser is zeroed at the path
        height). Freezes the current layer first."""
        from icefab.frames import to_part_frame
        from icefab.core import HeightMap

        sim_mod = _simulator
        self.freeze()
        job = self.job
        sim = job.simulation
        xy = to_part_frame(xy_base, "laser", job)
        tagged, true = sim_mod.laser_in_time(xy, float(dt_s), sim.laser_rate_hz,
                                              sim.laser_latency_s)
        surf = HeightMap(origin=self.origin, spacing=self.spacing, z=self.z)
        samples = sim_mod.laser_measure(surf, tagged, true, noise_mm=sim.laser_noise_mm,
                                        rng=self.rng_laser)
        return samples[:, 2] - z_ref_mm


def _chord_midpoints(xy: np.ndarray) -> np.ndarray:
    """Midpoints of a path's chords with repeated samples dropped (as
    ``icefab.sim.plan_layer_motion`` makes its segments)."""
    pts = xy
    if len(pts) > 1:
        step = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        pts = pts[np.concatenate([[True], step > _TINY_MM])]
    if len(pts) < 2:
        pts = np.vstack([pts[:1], pts[:1]])
    return 0.5 * (pts[:-1] + pts[1:])


def grid_for(motion, job, layers: int | None = None) -> tuple[np.ndarray, tuple[int, int],
                                                                float]:
    """The grid ``icefab simulate`` uses for these trajectories (first ``layers``
    layers): (origin (2,) mm, shape (ny, nx), spacing mm)."""
    sim = _simulator
    chosen = motion.layers[:layers] if layers else motion.layers
    hm = sim.grid_for((sim.plan_layer_motion(lm, job) for lm in chosen), job)
    return np.asarray(hm.origin, dtype=np.float64), hm.z.shape, float(hm.spacing)
