"""The icefab error family.

Every error a user can cause is an :class:`IcefabError` (a ``ValueError``) whose message
names the file or setting, the offending value, and what was expected. The CLI turns these
into one line on stderr and a non-zero exit; anything else escaping is a bug.
"""

from __future__ import annotations


class IcefabError(ValueError):
    """Base class of every error caused by input (files, settings, geometry)."""


class ConfigError(IcefabError):
    """A job setting is unknown, of the wrong type, or out of range."""


class MeshError(IcefabError):
    """A mesh file cannot be read, or its data cannot be used (empty, NaN, bad index)."""


class GeometryError(IcefabError):
    """Geometry that a stage cannot work with (e.g. a layer with no closable contour)."""


class WorkspaceError(IcefabError):
    """A path point is outside the robot workspace or needs a joint beyond its range.

    The message of a point or segment out of reach ends with the settings that move the
    part in the cell (:data:`MOVE_PART`), so the one line says what to change."""

    def __init__(self, message: str) -> None:
        reach = "workspace" in message or "beyond its range" in message
        # not twice: the placement checks name the settings that move the part already
        said = MOVE_PART in message or "cell.ee_origin_mm" in message
        super().__init__(message + MOVE_PART if reach and not said else message)


#: What moves the part relative to the robot (issue 11): appended to reach errors.
MOVE_PART = ("; move the part: cell.ee_origin_mm (where the part's origin lies in the robot "
             "base frame, mm), or its placement parts.translation / parts.rotation_deg")


class FlowError(IcefabError):
    """A valve program cannot be made: calibration table, valve limits, flow out of range."""


class StackFileError(IcefabError):
    """A saved stack, toolpath, trajectory or journal file is missing, truncated or corrupt."""


class SimulationError(IcefabError):
    """The build simulator cannot run these inputs (no deposition, bad sample arrays)."""


class OutputError(IcefabError):
    """Results cannot be written where asked (the output folder is a file, not writable)."""


class CellError(IcefabError):
    """A device link of the cell failed: unreachable host or port, a malformed or
    unexpected message, a device's error reply, a timeout, or a bad cell state folder."""


class CellRefused(CellError):
    """A device refused a command for a reason that sending it again cannot change (a
    path with more points than the controller stores, a point out of its reach, another
    protocol version): the build stops at once instead of reconnecting."""


def interruption(exc: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C or SIGTERM (a KeyboardInterrupt: ``icefab.cli.common.Terminated``) that
    ``exc`` was raised from, if any: ``exc`` itself, its cause or context, or theirs. C code
    and the interpreter wrap what a signal handler raises in their own errors (numba's
    dispatcher a SystemError, a class's ``__set_name__`` a RuntimeError, matplotlib's first
    import an ImportError)."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return e
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return None
