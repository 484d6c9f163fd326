"""Protocol fuzz of the valve firmware's host build (bounded; bench/fuzz_firmware.py runs
10 000+ cases): random and malformed frames and byte streams never crash or hang it, every
bad frame is answered with an error frame, and no valve is left open."""
from __future__ import annotations

import pytest

from icefab.cell.valve_fuzz import CLASSES, Fuzzer
from icefab.cell.valve_host import HostFirmware

from test_cell_valve import raw, valvectl  # noqa: F401  (the session build fixture)


@pytest.mark.parametrize("seed", [1, 2])
def test_fuzz_no_crash_no_hang_no_valve_open(valvectl, seed):  # noqa: F811
    with HostFirmware(valvectl, clock="virtual") as fw:
        port = raw(fw.pty)
        rep = Fuzzer(port, fw.alive, seed=seed).run(150)
        port.close()
        assert fw.alive()
    assert rep.failures == []
    assert rep.cases == 150
    assert set(rep.by_class) == set(CLASSES)       # every class drawn at least once
    assert rep.error_frames >= sum(n for c, n in rep.by_class.items() if CLASSES[c])
