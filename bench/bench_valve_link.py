"""Valve link throughput (issue 13): does the 115 200-baud link to the valve controller keep
ahead of the robot on the 300 mm bunny?

    python3 bench/bench_valve_link.py [--layers 0.02,0.1,0.3,0.5,0.7,0.9] [--no-write]

For representative layers of the bunny (``bench/meshes.py``, default job with the
end-effector origin at (340, 0) mm as in bench_motion.py so the bunny is in reach): every
path is planned (MTTS trajectories, travel and measurement paths included: the robot's
motion time) and every depositing path gets its valve program (icefab.flow). Each program
is then uploaded by the real driver (icefab.cell.valve) to the firmware's host build
through a pty, through a port that counts every byte and every command/reply exchange.

Line time at 115 200 baud 8N1 (11 520 bytes/s each way), the driver waiting for each reply:
``(bytes out + bytes in) / 11 520 + exchanges x L`` with the turnaround L = 1 ms (the
controller answers within its main loop; a PC UART or a USB adapter with a 1 ms latency
timer) and, for comparison, L = 16 ms (an FTDI adapter at its default latency timer).
Per path, what must be there before the trigger is what fits the controller's store
(12 288 bytes, the rest streams while playing); it can be uploaded and armed while the
previous depositing path plays (queued ARM, PROTOCOL.md 7), so the time available to path
k is the motion time from the start of the previous depositing path to the start of k.
"""
from __future__ import annotations

import argparse
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import serial  # noqa: E402

from _report import write_section  # noqa: E402
from icefab import Job, plan_motion  # noqa: E402
from icefab.cell import valve_frames as vf  # noqa: E402
from icefab.cell.valve import ValveController, program_bytes  # noqa: E402
from icefab.cell.valve_host import HostFirmware, build_host  # noqa: E402
from icefab.flow import n_pulses, plan_valves  # noqa: E402
from icefab.mesh import load_mesh  # noqa: E402
from icefab.paths import plan_paths  # noqa: E402
from icefab.regions import add_scaffold  # noqa: E402
from icefab.slicing import slice_mesh  # noqa: E402

HEADING = "## Valve link throughput on the bunny (issue 13)"
BYTES_S = 115200 / 10
ARM_OUT, ARM_IN, DONE_IN = 7 + 1, 7 + 6, 7 + 20      # ARM, its reply, the DONE event


class Counting:
    """A port that counts bytes and writes (one write = one command/reply exchange)."""

    def __init__(self, port):
        self.port, self.out, self.inn, self.writes = port, 0, 0, 0

    def write(self, data):
        self.out += len(data)
        self.writes += 1
        return self.port.write(data)

    def read(self, n):
        data = self.port.read(n)
        self.inn += len(data)
        return data

    def close(self):
        self.port.close()

    def take(self):
        got = (self.out, self.inn, self.writes)
        self.out = self.inn = self.writes = 0
        return got


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layers", default="0.02,0.1,0.3,0.5,0.7,0.9",
                    help="layer heights as fractions of the bunny's layers")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args()
    from meshes import big_mesh

    t_start = time.perf_counter()
    job = Job().replace(**{"cell.ee_origin_mm": [340.0, 0.0]})
    stack = add_scaffold(slice_mesh(load_mesh(big_mesh("bunny")), job), job)
    n = len(stack.layers)
    picks = sorted({min(n - 1, int(float(f) * n)) for f in args.layers.split(",")})
    areas = [lay.part.area + lay.scaffold.area for lay in stack.layers]
    picks = sorted(set(picks) | {int(np.argmax(areas))})
    sub = type(stack)(layers=tuple(stack.layers[i] for i in picks), job=job,
                      layer_thickness=stack.layer_thickness)
    tp = plan_paths(sub, job)
    print(f"{len(picks)} layers of {n} planned in {time.perf_counter() - t_start:.0f} s",
          flush=True)

    rows, worst = [], None
    with tempfile.TemporaryDirectory() as tmp:
        exe = build_host(tmp)
        with HostFirmware(exe, clock="virtual") as fw:
            port = Counting(serial.serial_for_url(fw.pty, baudrate=115200, timeout=0.002))
            ctl = ValveController(port, timeout_s=2.0)
            ctl.hello()
            for lp in tp.layers:
                t_layer = time.perf_counter()
                durations, need_s, need16_s, deposit = [], [], [], []
                total_bytes = streamed = pulses = exchanges = 0
                for path in lp.paths:
                    traj = plan_motion(path, job)
                    durations.append(float(traj.duration))
                    if not path.depositing:
                        need_s.append(0.0)
                        need16_s.append(0.0)
                        deposit.append(False)
                        continue
                    prog = plan_valves(traj, path.material, job)
                    data = program_bytes(prog)
                    pulses += n_pulses(prog)
                    ctl.abort()
                    port.take()
                    up = ctl.upload(0, data)
                    out, inn, ex = port.take()
                    out, inn, ex = out + ARM_OUT, inn + ARM_IN + DONE_IN, ex + 1
                    line = (out + inn) / BYTES_S
                    need_s.append(line + ex * 0.001)
                    need16_s.append(line + ex * 0.016)
                    deposit.append(True)
                    total_bytes += len(data)
                    streamed += len(data) - up.sent
                    exchanges += ex
                dur = np.array(durations)
                start = np.concatenate([[0.0], np.cumsum(dur)[:-1]])
                idx = np.flatnonzero(deposit)
                # available to path k: from the start of the previous depositing path
                # (the first of the layer: the travel before it)
                prev_start = np.concatenate([[0.0], start[idx[:-1]]]) if len(idx) else np.zeros(0)
                avail = start[idx] - prev_start
                slack = avail - np.array(need_s)[idx]
                slack16 = avail - np.array(need16_s)[idx]
                row = dict(layer=lp.index, z=lp.z, paths=len(lp.paths), dep=len(idx),
                           motion=float(dur.sum()), link=float(np.sum(need_s)),
                           link16=float(np.sum(need16_s)), bytes=total_bytes, pulses=pulses,
                           streamed=streamed, exchanges=exchanges,
                           min_slack=float(slack[1:].min()) if len(slack) > 1 else float("nan"),
                           waits=int(np.sum(slack[1:] < 0)), wait_s=float(-slack[1:][slack[1:] < 0].sum()),
                           waits16=int(np.sum(slack16[1:] < 0)),
                           wait16_s=float(-slack16[1:][slack16[1:] < 0].sum()),
                           first_need=float(need_s[idx[0]]) if len(idx) else 0.0,
                           secs=time.perf_counter() - t_layer)
                rows.append(row)
                print(row, flush=True)
                if worst is None or row["link"] / row["motion"] > worst["link"] / worst["motion"]:
                    worst = row
            ctl.close()

    table = "\n".join(
        f"| {r['layer']} ({r['z']:.1f} mm) | {r['paths']:,} / {r['dep']:,} | {r['motion']:.1f} | "
        f"{r['bytes'] / 1024:.1f} kB, {r['pulses']:,} pulses | {r['exchanges']:,} | {r['link']:.2f} | "
        f"**{r['motion'] / r['link']:.1f}x** | {r['min_slack']:.2f} s | {r['waits']} ({r['wait_s']:.2f} s) | "
        f"{r['link16']:.2f} ({r['motion'] / r['link16']:.1f}x) | {r['waits16']} ({r['wait16_s']:.2f} s) |"
        for r in rows)
    tot_m = sum(r["motion"] for r in rows)
    tot_l = sum(r["link"] for r in rows)
    text = f"""{HEADING}

`python3 bench/bench_valve_link.py` — {platform.machine()}, Python {platform.python_version()}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}. The 300 mm bunny (`bench/meshes.py`), default job with the end-effector origin at (340, 0) mm; layers at {args.layers} of the height plus the layer of largest area; every path's MTTS trajectory (travel and measurement included: the robot's motion time) and every depositing path's valve program (`icefab.flow`, FM). Each program was uploaded and verified by the real driver (`icefab.cell.valve`) to the firmware's host build through a pty and a byte-counting port; line time at 115 200 baud 8N1 (11 520 bytes/s each way) with the driver waiting for every reply: (bytes out + bytes in) / 11 520 + exchanges x turnaround, plus ARM and the DONE event per path. Turnaround L = 1 ms (the controller answers from its main loop; a PC UART or a USB adapter at a 1 ms latency timer); L = 16 ms for an FTDI adapter at its default latency timer.

| layer (z) | paths / depositing | motion (s) | programs | exchanges | link at L = 1 ms (s) | motion / link | least slack | paths the robot waits for (time) | link at L = 16 ms (s) | waits at 16 ms |
|---|---|---|---|---|---|---|---|---|---|---|
{table}

Over these layers the link needs {tot_l:.1f} s for {tot_m:.0f} s of motion: it keeps **{tot_m / tot_l:.0f} times** ahead on average (worst layer {worst['layer']}: {worst['motion'] / worst['link']:.1f}x). Per path ("least slack", "paths the robot waits for"): path k's program (what fits the 12 kB store; any rest streams while it plays, at {BYTES_S * 235 / 247 / 2:,.0f} FM pulses/s against the valve's 1 000 Hz limit) is uploaded, verified and its ARM queued while the previous depositing path plays; the slack is the time left over (the first path of each layer is not counted: it loads during the previous layer's end). Programs streamed while playing: {sum(r['streamed'] for r in rows):,} bytes in all.
"""
    print(text)
    if not args.no_write:
        write_section(HEADING, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
