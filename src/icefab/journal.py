"""The build journal: ``BUILD/journal.sqlite``, so a crash never loses a build (thesis 2.5).

SQLite (the standard library's ``sqlite3``) in write-ahead-log mode with
``synchronous=FULL``: a transaction that returned is on disk, whatever happens to the
process or the power afterwards; every step is one transaction. What it holds:

* ``meta``: the job and input digests (:func:`digest_file`, :func:`digest_text`) and the
  build's settings; a resume with other inputs is refused before anything moves.
* ``commands``: every command to the cell, **written before it is sent** (``sent`` NULL
  until the send returned) and its acknowledgement after (``acked``): ``seq`` is the
  command's sequence number, unique for the whole build; a command repeated after a crash
  carries its old ``seq`` (:meth:`Journal.command`), so the cell acknowledges it instead of
  executing it again. ``kind``: ``path`` (one trajectory with its valve program: ``layer``,
  ``item`` = the trajectory's index in the layer), ``layer_end``, ``stop``. ``done`` is set
  when the cell reported the path complete, ``cut`` when a cell fault cut it short.
* ``laser``: the laser samples of every measurement path as the cell returned them (npy
  bytes), journaled before the next path is sent: a real laser stores one path's values,
  so a resumed build takes the earlier paths of a layer's measurement from here.
* ``measurements``: every measurement (layer, laser samples as npy bytes, measured RMS).
* ``smf``: the SMF controller state and control action after the last two updates, as
  npz bytes (:func:`pack_arrays`), so a resumed build re-plans with exactly the action it
  had. Only the last is read; every one kept made a 1 200-layer bunny's journal 1 GB, 0.7
  of it SMF states (a hunt's), so older ones go in the transaction that adds a new one.
* ``events``: what happened and where (start, resume, cell faults, stop), for the report.

Rows are only ever added or completed, never rewritten with other content (``smf``
rows older than the last two are removed). What the runner asks per path or per layer
is indexed or kept in memory: a journal of the bunny's 555 000 commands answers in
milliseconds.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import sqlite3
import time
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from icefab.atomic import replace_durably
from icefab.errors import IcefabError


def remove_files(path: str | os.PathLike) -> None:
    """Remove the journal at ``path`` with the files SQLite keeps beside it (its WAL, the
    WAL's index, a rollback journal); close its connections first."""
    for f in (Path(path), *(Path(f"{path}-{x}") for x in ("wal", "shm", "journal"))):
        f.unlink(missing_ok=True)


SCHEMA_VERSION = 2   # 2: the laser table (version 1 journals ran on the stand-in cell)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS commands (
    seq INTEGER PRIMARY KEY, kind TEXT NOT NULL, layer INTEGER, item INTEGER,
    digest TEXT NOT NULL, created REAL NOT NULL, sent REAL, acked REAL, done REAL,
    cut INTEGER NOT NULL DEFAULT 0, UNIQUE (kind, layer, item));
CREATE TABLE IF NOT EXISTS laser (
    seq INTEGER PRIMARY KEY, samples BLOB NOT NULL, time REAL NOT NULL);
CREATE TABLE IF NOT EXISTS measurements (
    k INTEGER PRIMARY KEY, layer INTEGER NOT NULL, nominal_z REAL NOT NULL,
    samples BLOB NOT NULL, rms_measured REAL, time REAL NOT NULL);
CREATE TABLE IF NOT EXISTS smf (
    k INTEGER PRIMARY KEY, layer INTEGER NOT NULL, state BLOB NOT NULL, time REAL NOT NULL);
CREATE INDEX IF NOT EXISTS commands_open ON commands (seq) WHERE done IS NULL;
CREATE INDEX IF NOT EXISTS commands_cut ON commands (layer) WHERE cut;
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY AUTOINCREMENT, time REAL NOT NULL, kind TEXT NOT NULL,
    layer INTEGER, text TEXT NOT NULL);
"""


class JournalError(IcefabError):
    """The journal cannot be used: other inputs, another schema, a broken file."""


def digest_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def digest_file(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def digest_text(text: str) -> str:
    return digest_bytes(text.encode("utf-8"))


def pack_arrays(**arrays: Any) -> bytes:
    """npz bytes of named arrays (None entries left out)."""
    buf = io.BytesIO()
    np.savez(buf, **{k: np.asarray(v) for k, v in arrays.items() if v is not None})
    return buf.getvalue()


def unpack_arrays(data: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _samples_blob(samples: np.ndarray) -> bytes:
    """npy bytes of a float64 samples array (the laser and measurements tables)."""
    buf = io.BytesIO()
    np.save(buf, np.asarray(samples, dtype=np.float64), allow_pickle=False)
    return buf.getvalue()


def _samples(blob: bytes) -> np.ndarray:
    return np.load(io.BytesIO(blob), allow_pickle=False)


class Journal:
    """One build's journal (see the module docstring). Use :meth:`create` or :meth:`open`."""

    def __init__(self, path: Path, conn: sqlite3.Connection) -> None:
        self.path = path
        self._db = conn
        self._paths_done: int | None = None
        self._cut_layers: set[int] | None = None
        self._first_seq: int | None = None

    # ------------------------------------------------------------------ opening

    @staticmethod
    def _connect(path: Path) -> sqlite3.Connection:
        conn = sqlite3.connect(str(path), timeout=30.0, isolation_level=None)
        conn.execute("PRAGMA journal_mode=WAL")
        conn.execute("PRAGMA synchronous=FULL")
        return conn

    @classmethod
    def create(cls, path: str | os.PathLike, meta: Mapping[str, Any]) -> "Journal":
        """A new journal with ``meta`` (JSON-able values); JournalError if one exists."""
        path = Path(path)
        if path.exists():
            raise JournalError(f"{path}: a journal exists already (resume it with "
                               "'icefab build --resume')")
        # made whole under another name, then renamed into place: a build killed while
        # the file was opened left a journal with no tables, which every later command
        # took for a damaged one (a hunt's: SIGTERM or -9 at that instant)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.new")
        # what a build killed (-9) as it made its journal left (the folder's lock is held:
        # no other build makes one here now)
        for stale in path.parent.glob(f".{path.name}.*.new*"):
            stale.unlink(missing_ok=True)
        try:
            j = cls(tmp, cls._connect(tmp))
            with j._tx() as db:
                for stmt in _SCHEMA.strip().split(";"):
                    if stmt.strip():
                        db.execute(stmt)
                rows = {"schema": SCHEMA_VERSION, "created": time.time(), **meta}
                db.executemany("INSERT INTO meta VALUES (?, ?)",
                               [(k, json.dumps(v)) for k, v in rows.items()])
            j.close()   # the last connection: SQLite folds its WAL into the file
            replace_durably(tmp, path)
        except (sqlite3.Error, OSError) as exc:
            raise JournalError(f"{path}: the journal could not be created ({exc})") from None
        finally:
            remove_files(tmp)
        return cls(path, cls._connect(path))

    @classmethod
    def open(cls, path: str | os.PathLike) -> "Journal":
        """An existing journal; JournalError naming the file if it is not one."""
        path = Path(path)
        if not path.is_file():
            raise JournalError(f"{path}: no build journal here")
        try:
            j = cls(path, cls._connect(path))
            schema = j.meta().get("schema")
        except sqlite3.DatabaseError as exc:
            # a damaged journal (cut short, overwritten) is not a foreign file
            raise JournalError(f"{path}: not a build journal, or a damaged one ({exc}); "
                               "SQLite keeps a build's journal whole across crashes: a "
                               "damaged one was changed by something else") from None
        if schema != SCHEMA_VERSION:
            raise JournalError(f"{path}: journal schema {schema}, this icefab reads "
                               f"{SCHEMA_VERSION}")
        return j

    def add_indexes(self) -> None:
        """The indexes of this version on a journal made before them (the runner's resume
        calls it: a reader such as --status must not write)."""
        with self._tx() as db:
            for stmt in _SCHEMA.strip().split(";"):
                if stmt.strip().startswith("CREATE INDEX"):
                    db.execute(stmt)

    def close(self) -> None:
        self._db.close()

    class _Tx:
        def __init__(self, db: sqlite3.Connection, path: Path) -> None:
            self.db = db
            self.path = path

        def __enter__(self) -> sqlite3.Connection:
            try:
                self.db.execute("BEGIN IMMEDIATE")
            except sqlite3.OperationalError as exc:
                raise self._said(exc) from None
            return self.db

        def __exit__(self, exc_type, exc, tb) -> None:
            if exc_type is not None:
                try:
                    self.db.execute("ROLLBACK")
                except sqlite3.Error:   # the failed statement may have ended it already
                    pass
                if isinstance(exc, sqlite3.OperationalError):
                    raise self._said(exc) from None
                return
            try:
                self.db.execute("COMMIT")
            except sqlite3.OperationalError as exc:
                raise self._said(exc) from None

        def _said(self, exc: sqlite3.OperationalError) -> "JournalError":
            """One line naming the journal (a full disk ended a build, and every resume,
            with sqlite3's traceback: a hunt's); what was committed before stays."""
            return JournalError(f"{self.path}: the journal cannot be written ({exc}); free "
                                "space on its device (or fix what the message names) and "
                                "resume the build")

    def _tx(self) -> "Journal._Tx":
        """One transaction: committed (to disk, synchronous=FULL) when the block ends.
        sqlite3's operational errors (a full disk, a locked file) become a JournalError
        naming the journal."""
        return Journal._Tx(self._db, self.path)

    # ------------------------------------------------------------------ meta

    def meta(self) -> dict[str, Any]:
        return {k: json.loads(v) for k, v in self._db.execute("SELECT key, value FROM meta")}

    def set_meta(self, **values: Any) -> None:
        with self._tx() as db:
            db.executemany("INSERT OR REPLACE INTO meta VALUES (?, ?)",
                           [(k, json.dumps(v)) for k, v in values.items()])

    def check_digests(self, digests: Mapping[str, str]) -> None:
        """JournalError naming the first input whose digest differs from the journal's."""
        meta = self.meta()
        known = meta.get("digests", {})
        for name, value in digests.items():
            if known.get(name) != value:
                raise JournalError(f"{self.path}: {name} changed since the build started "
                                   f"(digest {str(known.get(name))[:12]} in the journal, "
                                   f"{value[:12]} now): resume with the same inputs and job, "
                                   "or start a new build in another folder")

    # ------------------------------------------------------------------ commands

    def command(self, kind: str, layer: int, item: int, digest: str) -> tuple[int, bool]:
        """The sequence number of a command, journaled before it is sent.

        A command already journaled (same kind, layer, item) keeps its old ``seq``: the
        repeat after a crash. Returns (seq, new). A repeat whose digest differs (the
        command's content changed) is a JournalError: it would not be the same command.
        """
        row = self._db.execute("SELECT seq, digest FROM commands WHERE kind=? AND layer=? "
                               "AND item=?", (kind, layer, item)).fetchone()
        if row is not None:
            if row[1] != digest:
                raise JournalError(f"{self.path}: {kind} {layer}/{item} was journaled with "
                                   "other content than is about to be sent again (seq "
                                   f"{row[0]}): the build's plan is not deterministic, or "
                                   "another icefab version started the build")
            return int(row[0]), False
        with self._tx() as db:
            seq = int(db.execute("SELECT COALESCE(MAX(seq), ?) + 1 FROM commands",
                                 (self.first_seq() - 1,)).fetchone()[0])
            db.execute("INSERT INTO commands (seq, kind, layer, item, digest, created) "
                       "VALUES (?, ?, ?, ?, ?, ?)", (seq, kind, layer, item, digest,
                                                    time.time()))
        return seq, True

    def first_seq(self) -> int:
        """The number of the build's first command: 1, or what :meth:`number_from` set."""
        if self._first_seq is None:
            row = self._db.execute("SELECT value FROM meta WHERE key='first_seq'").fetchone()
            self._first_seq = 1 if row is None else int(json.loads(row[0]))
        return self._first_seq

    def number_from(self, first: int) -> None:
        """Number the build's commands from ``first``: a new build on a cell that completed
        another build's commands up to ``first - 1`` (the cell answers a number at or below
        those "done" without running it). Only before the first command is journaled."""
        with self._tx() as db:
            if db.execute("SELECT COUNT(*) FROM commands").fetchone()[0]:
                raise JournalError(f"{self.path}: commands are journaled already; their "
                                   "numbers cannot change")
            db.execute("INSERT OR REPLACE INTO meta VALUES (?, ?)",
                       ("first_seq", json.dumps(int(first))))
        self._first_seq = int(first)

    def has_commands(self) -> bool:
        return self._db.execute("SELECT 1 FROM commands LIMIT 1").fetchone() is not None

    def _stamp(self, column: str, seq: int) -> None:
        with self._tx() as db:
            db.execute(f"UPDATE commands SET {column} = COALESCE({column}, ?) WHERE seq = ?",
                       (time.time(), seq))

    def sent(self, seq: int) -> None:
        self._stamp("sent", seq)

    def acked(self, seq: int) -> None:
        self._stamp("acked", seq)

    def done(self, seq: int, cut: bool = False) -> None:
        """The cell reported the path complete (``cut``: cut short by a cell fault)."""
        row = self._db.execute("SELECT kind, done, layer, cut FROM commands WHERE seq=?",
                               (seq,)).fetchone()
        with self._tx() as db:
            db.execute("UPDATE commands SET done = COALESCE(done, ?), cut = ? WHERE seq = ?",
                       (time.time(), int(cut), seq))
        if row is not None and row[0] == "path" and row[1] is None \
                and self._paths_done is not None:
            self._paths_done += 1
        if row is not None and self._cut_layers is not None:
            if cut:
                self._cut_layers.add(int(row[2]))
            elif row[3]:    # a cut command reported whole after all: read them again
                self._cut_layers = None

    def is_done(self, seq: int) -> bool:
        row = self._db.execute("SELECT done FROM commands WHERE seq=?", (seq,)).fetchone()
        return row is not None and row[0] is not None

    def highest_done(self) -> int:
        """The highest number of a path the cell completed to its end (not cut; layer ends
        are not paths: a robot's last done counts paths only), 0 before any."""
        row = self._db.execute("SELECT MAX(seq) FROM commands WHERE done IS NOT NULL AND "
                               "NOT cut AND kind != 'layer_end'").fetchone()
        return int(row[0] or 0)

    def is_cut(self, seq: int) -> bool:
        """Whether a cell fault cut command ``seq`` short."""
        row = self._db.execute("SELECT cut FROM commands WHERE seq=?", (seq,)).fetchone()
        return row is not None and bool(row[0])

    def commands(self, *, open_only: bool = False) -> list[dict[str, Any]]:
        """Every command in number order (``open_only``: those not done, by an index: the
        reconnection after a link fault read all 555 000 of a bunny's, 3 s and 360 MB
        each time, a hunt's)."""
        cur = self._db.execute("SELECT seq, kind, layer, item, digest, created, sent, acked, "
                               "done, cut FROM commands "
                               + ("WHERE done IS NULL " if open_only else "") + "ORDER BY seq")
        names = [d[0] for d in cur.description]
        return [dict(zip(names, r)) for r in cur]

    def done_items(self, layer: int) -> list[int]:
        """The trajectories of layer ``layer`` whose paths are done (deposition, travel
        and measurement; not a fault's measurement, whose items are another layer's)."""
        return [int(r[0]) for r in self._db.execute(
            "SELECT item FROM commands WHERE layer=? AND kind='path' AND done IS NOT NULL",
            (layer,))]

    def numbered_after(self, seq: int, layer: int) -> bool:
        """Whether a command of another layer than ``layer`` has a number above ``seq``."""
        return self._db.execute("SELECT 1 FROM commands WHERE seq > ? AND layer != ? LIMIT 1",
                                (seq, layer)).fetchone() is not None

    def paths_done(self) -> int:
        """Paths completed (counted once, then kept up to date by :meth:`done`: the
        runner asks after every path)."""
        if self._paths_done is None:
            self._paths_done = int(self._db.execute(
                "SELECT COUNT(*) FROM commands WHERE kind='path' AND done IS NOT NULL"
            ).fetchone()[0])
        return self._paths_done

    def cut_layers(self) -> set[int]:
        """Layers with a path a cell fault cut short (``done(seq, cut=True)``): read once,
        then kept up to date by :meth:`done` (the runner asks for every layer, three
        times over on a resume: a scan of the commands each time made a resume of the
        bunny near its end wait 5 minutes before the first path, deaf to --stop, a
        hunt's). A copy."""
        if self._cut_layers is None:
            self._cut_layers = {int(r[0]) for r in self._db.execute(
                "SELECT DISTINCT layer FROM commands WHERE cut")}
        return set(self._cut_layers)

    def layers_done(self) -> list[int]:
        return [int(r[0]) for r in self._db.execute(
            "SELECT layer FROM commands WHERE kind='layer_end' AND done IS NOT NULL "
            "ORDER BY layer")]

    # ------------------------------------------------------------------ measurements, SMF

    def laser(self, seq: int, samples: np.ndarray) -> None:
        """The raw laser samples of measurement path ``seq`` (kept once)."""
        with self._tx() as db:
            db.execute("INSERT OR IGNORE INTO laser VALUES (?, ?, ?)",
                       (seq, _samples_blob(samples), time.time()))

    def laser_of(self, seq: int) -> np.ndarray | None:
        row = self._db.execute("SELECT samples FROM laser WHERE seq=?", (seq,)).fetchone()
        return None if row is None else _samples(row[0])

    def measurement(self, k: int, layer: int, nominal_z: float, samples: np.ndarray,
                    rms_measured: float, smf_state: bytes | None = None) -> None:
        """The k-th measurement (layer ``layer``) and, given, the SMF state it led to, in
        one transaction: written apart, a build killed between them resumed with that
        layer measured and its update lost (a hunt's: 0.108 mm final RMS against 0.043)."""
        with self._tx() as db:
            db.execute("INSERT OR IGNORE INTO measurements VALUES (?, ?, ?, ?, ?, ?)",
                       (k, layer, nominal_z, _samples_blob(samples), rms_measured,
                        time.time()))
            if smf_state is not None:
                db.execute("INSERT OR IGNORE INTO smf VALUES (?, ?, ?, ?)",
                           (k, layer, smf_state, time.time()))
                db.execute("DELETE FROM smf WHERE k < ?", (k - 1,))   # only the last is read

    def measured_layers(self) -> set[int]:
        """The layers with a measurement (their samples not read)."""
        return {int(r[0]) for r in self._db.execute("SELECT layer FROM measurements")}

    def measurements(self, *, samples: bool = True, last: bool = False
                     ) -> list[dict[str, Any]]:
        """The measurements in order, each with its laser samples unless ``samples`` is
        False; ``last``: only the latest (a list of at most one). The runner reads the
        samples of the last one only: all of a bunny's took 230 MB for the whole build
        after a resume (a hunt's)."""
        out = []
        cols = "k, layer, nominal_z, rms_measured, time" + (", samples" if samples else "")
        for row in self._db.execute(f"SELECT {cols} FROM measurements ORDER BY k "
                                    + ("DESC LIMIT 1" if last else "")):
            m = dict(zip(("k", "layer", "nominal_z", "rms_measured", "time"), row[:5]))
            if samples:
                m["samples"] = _samples(row[5])
            out.append(m)
        return out

    def last_smf(self) -> tuple[int, int, bytes] | None:
        row = self._db.execute("SELECT k, layer, state FROM smf ORDER BY k DESC LIMIT 1"
                               ).fetchone()
        return None if row is None else (int(row[0]), int(row[1]), bytes(row[2]))

    # ------------------------------------------------------------------ events

    def event(self, kind: str, text: str, layer: int | None = None) -> None:
        with self._tx() as db:
            db.execute("INSERT INTO events (time, kind, layer, text) VALUES (?, ?, ?, ?)",
                       (time.time(), kind, layer, text))

    def events(self) -> list[dict[str, Any]]:
        cur = self._db.execute("SELECT time, kind, layer, text FROM events ORDER BY id")
        return [{"time": t, "kind": k, "layer": lay, "text": x} for t, k, lay, x in cur]

    def __iter__(self) -> Iterator[dict[str, Any]]:  # pragma: no cover - convenience
        return iter(self.commands())
