"""Worker pools: never more workers than cores, and workers die with their parent
(issue 10: cpus = 1000000 forked hundreds of workers, 230 orphans stayed after a kill)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from icefab import Job
from icefab.parallel import machine_cores, n_workers


def test_cpus_beyond_the_machine_are_capped():
    assert n_workers(Job().replace(**{"cell.cpus": 1024})) == machine_cores()
    assert n_workers(Job().replace(**{"cell.cpus": 0})) == machine_cores()
    assert n_workers(Job().replace(**{"cell.cpus": 1})) == 1


def _children(pid: int) -> set[int]:
    out: set[int] = set()
    for task in Path(f"/proc/{pid}/task").iterdir():
        out |= {int(c) for c in (task / "children").read_text().split()}
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state not in ("Z", "X")


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(),
                    reason="needs Linux /proc to find the pool's workers")
def test_pool_workers_die_when_the_parent_is_killed(tmp_path):
    script = textwrap.dedent("""
        import sys, time
        from icefab import Job
        from icefab.parallel import parallel_map
        def nap(x):
            time.sleep(60)
            return x
        if __name__ == "__main__":
            print("go", flush=True)
            parallel_map(nap, list(range(8)), Job().replace(**{"cell.cpus": 1024}),
                         min_items=1)
    """)
    (tmp_path / "pool.py").write_text(script)
    proc = subprocess.Popen([sys.executable, str(tmp_path / "pool.py")],
                            stdout=subprocess.PIPE, cwd=tmp_path, env=os.environ.copy())
    _alive_workers: set[int] = set()
    try:
        assert proc.stdout.readline().strip() == b"go"
        workers: set[int] = set()
        _alive_workers = workers
        deadline = time.monotonic() + 60
        want = min(machine_cores(), 8)
        while len(workers) < want and time.monotonic() < deadline:
            time.sleep(0.2)
            workers |= {c for c in _children(proc.pid) if _alive(c)}
        assert len(workers) == want  # capped at the cores, not 1024
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        deadline = time.monotonic() + 10
        while any(_alive(w) for w in workers) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not [w for w in workers if _alive(w)], "pool workers outlived their parent"
    finally:
        if proc.poll() is None:
            proc.kill()
        for w in _alive_workers:
            if _alive(w):
                os.kill(w, signal.SIGKILL)  # never leave orphans behind a failed run


def _square(x: int) -> int:
    return x * x


@pytest.mark.parametrize("cpus", [1, 2])
def test_parallel_imap_yields_in_order_and_reports_progress(cpus):
    from icefab.parallel import parallel_imap
    job = Job().replace(**{"cell.cpus": cpus})
    calls = []
    got = list(parallel_imap(_square, list(range(100)), job, chunk_items=3,
                             progress=lambda d, t: calls.append((d, t))))
    assert got == [x * x for x in range(100)]
    assert calls[-1] == (100, 100) and [d for d, _ in calls] == sorted(d for d, _ in calls)


def test_parallel_imap_holds_a_bounded_window_and_stops_when_the_consumer_does():
    from icefab.parallel import parallel_imap
    job = Job().replace(**{"cell.cpus": 2})
    calls = []
    stream = parallel_imap(_square, list(range(10_000)), job, chunk_items=5, window=2,
                           progress=lambda d, t: calls.append(d))
    assert next(stream) == 0
    stream.close()            # the pool ends; the chunks not yet started are dropped
    assert calls[-1] <= 5 * (2 * 2 + 1)


def _slow(x: int) -> int:
    time.sleep(0.25)
    return x


@pytest.mark.parametrize("streamed", [False, True])
def test_an_interrupted_map_does_not_run_the_rest_first(streamed):
    # leaving a 'with ProcessPoolExecutor' waits for every submitted item: a build stopped
    # while it planned its paths ran the rest of the stage first (over 60 s in CI)
    from icefab.parallel import parallel_imap, parallel_map

    job = Job().replace(**{"cell.cpus": 2})    # a pool on 2 cores (serial on 1: at once too)

    def stop(done, total):
        raise KeyboardInterrupt

    items = list(range(200))       # 25 s of work on 2 workers
    t0 = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        if streamed:
            for _ in parallel_imap(_slow, items, job, chunk_items=2, progress=stop):
                pass
        else:
            parallel_map(_slow, items, job, progress=stop)
    assert time.monotonic() - t0 < 8.0


def _fails_first(x):
    if x == 0:
        raise ValueError("item 0")
    time.sleep(0.5)
    return x


def test_a_failed_map_leaves_nothing_for_the_exit_hook_to_wake():
    """A map that fails shuts its pool down without waiting and takes it off
    concurrent.futures' exit hook, which on CPython 3.11 could write to the manager
    thread's closed pipe and print "Exception ignored ... Bad file descriptor" after the
    command's one-line error (a hunt's simulate, 2 runs in 3)."""
    import concurrent.futures.process as cfp

    from icefab.parallel import parallel_map

    job = Job().replace(**{"cell.cpus": 2})
    before = set(cfp._threads_wakeups)
    with pytest.raises(ValueError, match="item 0"):
        parallel_map(_fails_first, [0, 1], job, min_items=2)
    assert set(cfp._threads_wakeups) <= before


@pytest.mark.parametrize("stage", ["paths", "plan"])
def test_sigterm_to_the_process_group_ends_a_command_at_once(tmp_path, stage):
    """'timeout' and service managers send SIGTERM to the whole process group: the pool's
    workers end first, and the pool's own thread then failed on the items the command had
    cancelled (CPython 3.11's InvalidStateError) before closing its queue, so the command
    said "terminated" and waited at exit for ever (a hunt's, 4 runs in 10). It ends with
    its one line, exit 143, and leaves no temporary folder or worker behind."""
    inputs = {"paths": ["demo", "--layers", "0"], "plan": []}
    if stage == "plan":   # a toolpath file to plan from
        from icefab.cli import main
        assert main(["paths", "demo", "-o", str(tmp_path / "p")]) == 0
        inputs["plan"] = [str(tmp_path / "p" / "toolpaths.npz")]
    proc = subprocess.Popen([sys.executable, "-m", "icefab", stage, *inputs[stage], "-o",
                             str(tmp_path / "out")], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                            start_new_session=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    label = {"paths": "paths: ", "plan": "planning: "}[stage]   # its progress lines
    try:
        seen = ""
        while label not in seen:    # its workers are at work
            line = proc.stderr.readline()
            assert line, seen
            seen += line
        workers = set(_children(proc.pid))
        assert workers
        os.killpg(proc.pid, signal.SIGTERM)
        err = proc.communicate(timeout=60)[1]
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 143, err
    said = [ln for ln in err.splitlines() if not ln.startswith(label)]
    assert said == [f"icefab {stage}: terminated"], err
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.")]
    deadline = time.monotonic() + 10
    while any(_alive(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [w for w in workers if _alive(w)]


@pytest.mark.skipif(machine_cores() < 2, reason="a pool needs 2 cores (serial on 1)")
@pytest.mark.parametrize("where", ["between two workers' starts", "before its thread runs"])
def test_a_map_interrupted_as_its_pool_starts_lets_the_process_end(tmp_path, where):
    # a build stopped at once hung at its exit in CI (stop 48): the stop came as the pool
    # forked its workers, before the pool's thread that ends them ran, and multiprocessing
    # joins its children at exit. The interruption is put into those instants (CPython's
    # own steps of ProcessPoolExecutor).
    import concurrent.futures.process as cfp
    step = {"between two workers' starts": "_spawn_process",
            "before its thread runs": "_start_executor_manager_thread"}[where]
    if not hasattr(cfp.ProcessPoolExecutor, step):
        pytest.skip(f"this Python's ProcessPoolExecutor has no {step} to interrupt")
    script = textwrap.dedent(f"""
        import concurrent.futures.process as cfp
        from icefab import Job
        from icefab.parallel import parallel_map
        P = cfp.ProcessPoolExecutor
        step = P.{step}
        def interrupted(self):
            if "{step}" == "_spawn_process":
                step(self)     # one worker started, the next not
            else:              # every worker started, the thread not
                self._launch_processes()
            raise KeyboardInterrupt
        P.{step} = interrupted
        try:
            parallel_map(abs, list(range(100)), Job().replace(**{{"cell.cpus": 2}}))
        except KeyboardInterrupt:
            print("interrupted", flush=True)
    """)
    (tmp_path / "pool.py").write_text(script)
    proc = subprocess.run([sys.executable, str(tmp_path / "pool.py")], capture_output=True,
                          text=True, cwd=tmp_path, timeout=60)
    assert proc.returncode == 0 and proc.stdout == "interrupted\n", proc.stderr


def _worker_signals(_: int) -> tuple[bool, bool]:
    return (signal.getsignal(signal.SIGINT) is signal.SIG_IGN,
            signal.getsignal(signal.SIGTERM) is signal.SIG_DFL)


@pytest.mark.skipif(machine_cores() < 2, reason="a pool needs 2 cores (serial on 1)")
def test_pool_workers_leave_signals_to_their_parent():
    # a terminal's Ctrl-C reaches the whole process group: a worker waiting for its next
    # item printed a KeyboardInterrupt traceback; SIGTERM to a build's workers raised the
    # command's Terminated in each, each printing a traceback (a check's)
    from icefab.parallel import parallel_map

    old = signal.signal(signal.SIGTERM, lambda *a: None)   # what a command installs
    try:
        got = parallel_map(_worker_signals, list(range(40)), Job().replace(
            **{"cell.cpus": 2}), min_items=1)
    finally:
        signal.signal(signal.SIGTERM, old)
    assert set(got) == {(True, True)}
