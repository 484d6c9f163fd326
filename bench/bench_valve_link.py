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
(12 288 bytes, the rest streams while playing); programs are uploaded up to 4 ahead (the
controller's queue) and armed while the previous path plays (queued ARM, PROTOCOL.md 7);
:func:`robot_waits` replays a layer and says how long the robot would wait.
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


def robot_waits(dur: np.ndarray, idx: np.ndarray, need: np.ndarray, arm_s: float,
                queue: int = vf.QUEUE) -> tuple[np.ndarray, np.ndarray]:
    """How long the robot waits at each depositing path for the valve link.

    dur: (n,) s, motion time of every path of the layer in order; idx: (m,) indices of the
    depositing paths; need: (m,) s, link time of each one's program (upload, verify, ARM).
    The link works through the programs in order, one at a time; program j can be begun
    once a queue slot is free (program j - queue has finished playing; the controller
    queues 4 programs per valve, counted here over both valves: conservative) and must be
    armed before its trigger, when the robot reaches path j; its ARM (``arm_s``, part of
    ``need``) can be sent only once path j - 1 plays (one ARM is queued at a time). A late program delays the
    robot and so everything after it. The layer starts with the link idle at time 0 (its
    first programs are not preloaded during the previous layer). Returns (waits (m,) s,
    slack (m,) s: trigger time minus the time the program was ready)."""
    start = np.concatenate([[0.0], np.cumsum(dur)[:-1]])
    m = len(idx)
    waits, slack = np.zeros(m), np.zeros(m)
    ends = np.zeros(m)
    link_free, delay = 0.0, 0.0
    for j in range(m):
        can_begin = link_free if j < queue else max(link_free, ends[j - queue])
        uploaded = can_begin + need[j] - arm_s       # upload and verify
        link_free = uploaded
        ready = uploaded if j == 0 else max(uploaded, ends[j - 1] - dur[idx[j - 1]])
        ready += arm_s                               # ARM, once path j - 1 plays
        trigger = start[idx[j]] + delay
        if ready > trigger:
            waits[j] = ready - trigger
            delay += waits[j]
            trigger = ready
        slack[j] = trigger - ready
        ends[j] = trigger + dur[idx[j]]
    return waits, slack


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
                idx = np.flatnonzero(deposit)
                arm_line = (ARM_OUT + ARM_IN) / BYTES_S
                waits1, slack1 = robot_waits(dur, idx, np.array(need_s)[idx], arm_line + 0.001)
                waits16, slack16 = robot_waits(dur, idx, np.array(need16_s)[idx], arm_line + 0.016)
                row = dict(layer=lp.index, z=lp.z, paths=len(lp.paths), dep=len(idx),
                           motion=float(dur.sum()), link=float(np.sum(need_s)),
                           link16=float(np.sum(need16_s)), bytes=total_bytes, pulses=pulses,
                           streamed=streamed, exchanges=exchanges,
                           min_slack=float(slack1[1:].min()) if len(slack1) > 1 else float("nan"),
                           first_wait=float(waits1[0]) if len(waits1) else 0.0,
                           waits=int(np.sum(waits1 > 0)), wait_s=float(waits1.sum()),
                           waits16=int(np.sum(waits16 > 0)), wait16_s=float(waits16.sum()),
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

| layer (z) | paths / depositing | motion (s) | programs | exchanges | link at L = 1 ms (s) | motion / link | least slack after the first path | paths the robot waits for (total wait) | link at L = 16 ms (s) | waits at 16 ms |
|---|---|---|---|---|---|---|---|---|---|---|
{table}

Over these layers the link needs {tot_l:.1f} s for {tot_m:.0f} s of motion: it keeps **{tot_m / tot_l:.0f} times** ahead on average (worst layer {worst['layer']}: {worst['motion'] / worst['link']:.1f}x). Per path ("least slack", "paths the robot waits for"): the driver works through the layer's programs in order, each uploaded (what fits the 12 kB store; any rest streams while it plays, at {BYTES_S * 235 / 247 / 2:,.0f} FM pulses/s against the valve's 1 000 Hz limit), verified and armed (a queued ARM while the previous path plays) up to 4 programs ahead of the robot (the controller's queue; counted over both valves, conservatively); the robot waits when it reaches a path whose program is not armed yet, and that delay carries on. Each layer starts with the link idle (nothing preloaded while the previous layer ends), so the robot waits at every layer's first path for that program's upload ({min(r['first_wait'] for r in rows):.2f}-{max(r['first_wait'] for r in rows):.2f} s here at L = 1 ms; a runner that uploads it during the previous layer's last path or measurement avoids that); "least slack after the first path" is the smallest margin by which a later program was armed before its trigger. Programs streamed while playing: {sum(r['streamed'] for r in rows):,} bytes in all.
"""
    print(text)
    if not args.no_write:
        write_section(HEADING, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
