"""The subset of the Keyence LK-G RS-232C command protocol icefab uses (thesis 2.3.2, 5.2.1).

Shared by the driver (:mod:`icefab.cell.laser`) and the emulator
(:mod:`icefab.cell.laser_emulator`), so both ends read and write one format.

Source: the LK-G Series User Manual (LK-G-M-NO5-E), chapter 5 "RS-232C": the command
format (p. 5-5: commands and responses delimited by CR, upper or lower case, the response
repeats the command as its header, errors are ``ER,<command>,<code>`` with the codes of
:data:`ERRORS`), the measurement value format (p. 5-6: a sign and seven characters with
the decimal point, right-aligned; ``+FFFFFFF`` / ``-FFFFFFF`` beyond the range,
``XXXXXXXX`` when no value). The storage commands (``AS`` start, ``AP`` stop, ``AQ``
initialise, ``AN`` status, ``AO`` output) are implemented after our reading of the
manual's command list; their response layouts (``AN,<storing 0/1>,<count>``,
``AO,<value>,<value>,...``) must be checked against the manual before a real controller
is connected. Serial settings: 115 200 bit/s, 8N1 (thesis Table 2-3). Storage holds
65 536 values (Table 2-3, "controller memory").

How icefab measures a path (thesis 5.2.1): ``AQ`` (clear) and ``AS`` (start) before the
robot runs the measurement path; the C40 raises the laser's timing input for the path and
the controller stores one value every storage cycle (10 ms: 100 Hz) while it is high; after
the path ``AP`` (stop) and ``AO,1`` read the values out. ``M0`` reads the current values
(both outputs) at once.
"""

from __future__ import annotations

import math
import re

from icefab.errors import CellError

BAUD = 115_200
CR = b"\r"
STORAGE_CAPACITY = 65_536
RATE_HZ = 100.0

#: error codes of ``ER,<command>,<code>`` replies (manual p. 5-5)
ERRORS = {"00": "command error", "01": "status error", "20": "command length error",
          "21": "parameter count error", "22": "invalid parameter error",
          "88": "timeout error", "99": "other error"}

#: commands: name -> number of parameters
COMMANDS = {"M0": 0, "AS": 0, "AP": 0, "AQ": 0, "AN": 0, "AO": 1}

MAX_COMMAND = 32          # characters before CR; longer is a length error
OVER = "+FFFFFFF"
UNDER = "-FFFFFFF"
INVALID = "XXXXXXXX"
RANGE_MM = 99.9999        # what the format can show at four decimals


def format_value(value_mm: float) -> str:
    """A measured value in the LK-G format: ``+01.2345`` (mm, four decimals), ``+FFFFFFF``
    / ``-FFFFFFF`` beyond the format's range, ``XXXXXXXX`` for NaN (no value)."""
    if math.isnan(value_mm):
        return INVALID
    if value_mm > RANGE_MM:
        return OVER
    if value_mm < -RANGE_MM:
        return UNDER
    text = f"{value_mm:+08.4f}"
    return "+00.0000" if text == "-00.0000" else text


def parse_value(text: str) -> float:
    """A value field back to mm; NaN for the over/under-range and no-value marks.
    CellError if it is none of these."""
    if text in (OVER, UNDER, INVALID):
        return math.nan
    # a sign and seven characters, digits around one decimal point (manual p. 5-6:
    # "+01.2345"); float() alone took "+1.0E300", "+nan    " and "+1_2.345", and one
    # corrupted readout drove SMF to its limit (a hunt's)
    if not _VALUE.fullmatch(text) or abs(float(text)) > RANGE_MM:
        raise CellError(f"laser: malformed measurement value {text[:16]!r}")
    return float(text)


_VALUE = re.compile(r"[+-](?=[0-9.]{7}$)[0-9]+\.[0-9]+")
