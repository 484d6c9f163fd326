"""Protocol fuzz of the valve firmware (issue 13): >= 10 000 random and malformed frames and
byte streams into the host build of the real C core, through its pty.

    python3 bench/fuzz_firmware.py [--cases N] [--seed S] [--no-write]

After every case a probe (HELLO + STATUS) must be answered within 2 s (no hang), the
process must be alive (no crash), the classes that are bad input must have drawn an error
frame, and once nothing plays every valve must be closed (an ABORT follows any case that
left the controller armed or loaded). Prints the counts and writes them to BENCHMARKS.md
(section "Valve firmware: protocol fuzz").
"""
from __future__ import annotations

import argparse
import platform
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import serial  # noqa: E402

from _report import write_section  # noqa: E402
from icefab.cell.valve_fuzz import CLASSES, Fuzzer  # noqa: E402
from icefab.cell.valve_host import HostFirmware, build_host  # noqa: E402

HEADING = "## Valve firmware: protocol fuzz (issue 13)"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=10000)
    ap.add_argument("--seed", type=int, default=13)
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        exe = build_host(tmp)
        with HostFirmware(exe, clock="virtual") as fw:
            port = serial.serial_for_url(fw.pty, baudrate=115200, timeout=0.005)
            rep = Fuzzer(port, fw.alive, seed=args.seed).run(args.cases)
            port.close()
            alive = fw.alive()
        code = fw.proc.returncode
    rows = "\n".join(f"| {c} | {'yes' if CLASSES[c] else 'answered'} | {rep.by_class[c]:,} |"
                     for c in CLASSES)
    verdict = "no failure" if not rep.failures else f"{len(rep.failures)} FAILURES"
    text = f"""{HEADING}

`python3 bench/fuzz_firmware.py --cases {args.cases} --seed {args.seed}` — {platform.machine()}, Python {platform.python_version()}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}; the host build of the firmware's C core (`firmware/host`, virtual clock) on a pty, driven by `icefab.cell.valve_fuzz`.

**{rep.cases:,} cases, {rep.bytes_sent:,} bytes sent, {rep.error_frames:,} error frames received, {rep.plays:,} plays with garbage thrown in: {verdict}**; the process alive to the end (exit status {code} on SIGTERM), slowest probe answered in {rep.max_probe_s * 1000:.0f} ms, {rep.seconds:.0f} s in all (truncated frames wait the 50 ms byte timeout).

After every case: HELLO + STATUS answered within 2 s (no hang), process alive (no crash), an error frame for each case of bad input, every valve closed once nothing plays (and after the ABORT that follows any armed or loaded state).

| case class | must draw an error frame | cases |
|---|---|---|
{rows}
"""
    print(text)
    for f in rep.failures[:20]:
        print("FAILURE", f)
    if not args.no_write:
        write_section(HEADING, text)
    return 0 if not rep.failures and alive else 1


if __name__ == "__main__":
    sys.exit(main())
