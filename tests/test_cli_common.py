"""CLI framework: one-line errors, exit codes, atomic output folders, progress."""
import io
from pathlib import Path

import pytest

from icefab.cli import main
from icefab.cli.common import Progress, output_dir


def test_output_dir_appears_only_on_success(tmp_path):
    target = tmp_path / "out"
    with pytest.raises(RuntimeError):
        with output_dir(target, "test") as d:
            (d / "half.txt").write_text("x")
            raise RuntimeError("stage failed")
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []
    with output_dir(target, "test") as d:
        (d / "a.txt").write_text("1")
    assert (target / "a.txt").read_text() == "1"


def test_output_dir_keeps_old_results_when_a_rerun_fails(tmp_path):
    target = tmp_path / "out"
    with output_dir(target, "test") as d:
        (d / "a.txt").write_text("old")
    with pytest.raises(ValueError):
        with output_dir(target, "test") as d:
            (d / "a.txt").write_text("new")
            raise ValueError
    assert (target / "a.txt").read_text() == "old"


def test_progress_prints_final_line():
    stream = io.StringIO()
    p = Progress("slicing", stream=stream)
    for i in range(1, 101):
        p(i, 100)
    lines = stream.getvalue().splitlines()
    assert lines[-1].startswith("slicing: 100/100 (100 %")


def test_help_lists_the_subcommands(capsys):
    with pytest.raises(SystemExit) as ex:
        main(["--help"])
    assert ex.value.code == 0
    assert "COMMAND" in capsys.readouterr().out


def test_parse_layers():
    import pytest as _pytest

    from icefab.cli.common import parse_layers
    from icefab.errors import ConfigError

    assert parse_layers(None, 101) == [0, 33, 67, 100]
    assert parse_layers("5, 7", 10) == [5, 7]
    assert parse_layers("7,1,7,1,1", 10) == [7, 1]   # drawn once each (a tester's 1,1,1)
    assert parse_layers(None, 0) == []
    for bad in ("a,b", "10", "-1", ","):
        with _pytest.raises(ConfigError, match="--layers"):
            parse_layers(bad, 10)


def test_output_dir_leaves_other_files_and_uses_normal_modes(tmp_path):
    """A command writing into the folder it read from (paths into the slice folder) keeps
    the other files; results get the umask's modes, not mkstemp's 0600."""
    import os

    mask = os.umask(0o022)  # read the umask (a test may; icefab itself never does)
    os.umask(mask)
    file_mode = 0o666 & ~mask
    target = tmp_path / "out"
    target.mkdir()
    (target / "stack.npz").write_text("input")
    (target / "paths.png").write_text("old picture")
    with output_dir(target, "test") as d:
        (d / "paths.png").write_text("new picture")
        (d / "toolpaths.npz").write_text("new")
    assert (target / "stack.npz").read_text() == "input"
    assert (target / "paths.png").read_text() == "new picture"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    for name in ("paths.png", "toolpaths.npz"):
        assert os.stat(target / name).st_mode & 0o777 == file_mode


def test_output_to_a_file_is_one_line_error(tmp_path, capsys):
    from icefab.errors import OutputError

    afile = tmp_path / "afile"
    afile.write_text("keep me")
    with pytest.raises(OutputError, match="exists and is not a folder"):
        with output_dir(afile, "test"):
            pass
    # named as what it is, and before any work (it was found when the results were
    # written: "cannot create the output folder (File exists)", a tester's)
    with pytest.raises(OutputError, match=f"-o {afile}/sub: {afile} is a file, not a folder"):
        with output_dir(afile / "sub", "test"):
            pass
    assert afile.read_text() == "keep me"
    for out in (afile, afile / "sub"):
        assert main(["tune", "--gains", "1,0.33,0", "--layers", "60", "-o", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "icefab tune: error: -o" in err[0]
    assert afile.read_text() == "keep me"


def test_os_errors_become_one_line(monkeypatch, capsys):
    import icefab.cli.tune_cmd as tune_cmd

    def boom(args):
        raise PermissionError(13, "Permission denied", "/root/out/x.png")

    monkeypatch.setattr(tune_cmd, "run", boom)
    assert main(["tune", "--gains", "1,0.33,0"]) == 2
    assert capsys.readouterr().err.strip() == \
        "icefab tune: error: /root/out/x.png: Permission denied"


def test_a_reader_that_leaves_is_no_error_but_a_broken_link_is(monkeypatch, capsys):
    # 'icefab build --status B | head -1' said "error: Broken pipe" and exit 2; a pipe
    # broken elsewhere (a cell's socket) is still an error
    import os
    import subprocess
    import sys

    r, w = os.pipe()
    os.close(r)
    try:
        p = subprocess.run([sys.executable, "-m", "icefab", "tune", "--json"], stdout=w,
                           stderr=subprocess.PIPE, text=True)
    finally:
        os.close(w)
    assert p.returncode == 141 and p.stderr == ""
    import icefab.cli.tune_cmd as tune_cmd

    def boom(args):
        raise BrokenPipeError(32, "Broken pipe")

    monkeypatch.setattr(tune_cmd, "run", boom)
    assert main(["tune", "--gains", "1,0.33,0"]) == 2
    assert "error: Broken pipe" in capsys.readouterr().err


def test_slice_then_paths_into_the_same_folder(tmp_path, capsys):
    """`icefab slice m.stl -o out; icefab paths out/stack.npz -o out`: both results end up
    in out; a failing rerun (bad --layers) changes nothing there."""
    import trimesh

    stl = tmp_path / "tube.stl"
    tm = trimesh.creation.annulus(r_min=4, r_max=12, height=3, sections=48)
    tm.apply_translation((0, 0, 1.5))
    stl.write_bytes(tm.export(file_type="stl"))
    out = tmp_path / "out"
    job = tmp_path / "job.toml"
    job.write_text("[slicing]\nlayer_thickness_mm = 1.0\n")
    assert main(["slice", str(stl), "-c", str(job), "-o", str(out)]) == 0
    assert main(["paths", str(out / "stack.npz"), "-c", str(job), "-o", str(out)]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == [".icefab-paths", ".icefab-slice", "layers.png", "paths.png", "stack.npz",
                     "toolpaths.npz"]  # each command's record of what it wrote
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    capsys.readouterr()
    assert main(["paths", str(out / "stack.npz"), "-o", str(out), "--layers", "7"]) == 2
    assert "--layers" in capsys.readouterr().err
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["job.toml", "out", "tube.stl"]


@pytest.mark.parametrize("command", [
    ["demo"], ["slice", "MISSING.stl"], ["paths", "MISSING.stl"], ["plan", "MISSING.npz"],
    ["valves", "MISSING.npz"], ["simulate", "MISSING.npz"],
    ["tune", "--gains", "1,0.33,0", "--layers", "20"]])
def test_output_to_a_file_is_refused_before_any_work(tmp_path, capsys, command):
    # the input does not even exist: the -o check comes first, so a long job is not run
    # only to fail when its results are written
    afile = tmp_path / "afile"
    afile.write_text("keep me")
    assert main(command + ["-o", str(afile)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith(f"-o {afile}: exists and is not a folder")
    assert afile.read_text() == "keep me"


def test_output_dir_removes_only_its_commands_stale_results(tmp_path):
    target = tmp_path / "out"
    target.mkdir()
    (target / "stack.npz").write_text("input, not written by this command")
    with output_dir(target, "one") as d:
        (d / "result.npz").write_text("1")
        (d / "extra.gcode").write_text("1")
        (d / "layer_0009").mkdir()
        (d / "layer_0009" / "p.bin").write_text("1")
    with output_dir(target, "other") as d:  # another command's results are not touched
        (d / "theirs.png").write_text("2")
    with output_dir(target, "one") as d:
        (d / "result.npz").write_text("3")
    assert sorted(p.name for p in target.iterdir() if not p.name.startswith(".")) == [
        "result.npz", "stack.npz", "theirs.png"]
    assert (target / "result.npz").read_text() == "3"
    assert (target / ".icefab-one").read_text() == "result.npz\n"
    # a record naming something outside the folder removes nothing there
    (target / ".icefab-one").write_text("../outside\n..\n.\n\n.icefab-other\n")
    (tmp_path / "outside").write_text("keep")
    with output_dir(target, "one") as d:
        (d / "result.npz").write_text("4")
    assert (tmp_path / "outside").read_text() == "keep"
    assert (target / ".icefab-other").exists() and (target / "stack.npz").exists()


@pytest.mark.parametrize("command", [
    ["slice", "MISSING.stl"], ["paths", "MISSING.stl"], ["plan", "MISSING.npz"],
    ["valves", "MISSING.npz"], ["export", "ruled", "MISSING.npz"]])
@pytest.mark.parametrize("layers", ["a,b", ",", "1,x", "2.5"])
def test_a_layer_list_that_is_no_list_of_numbers_is_refused_before_any_work(
        tmp_path, capsys, command, layers):
    # a docs hunt's 'icefab slice box.stl --layers a,b' was refused after slicing; the
    # input does not even exist: the option is read first (its range needs the layers)
    with pytest.raises(SystemExit) as exc:
        main(command + ["-o", str(tmp_path / "out"), "--layers", layers])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].endswith(f"error: argument --layers: {layers!r}: expected "
                            "comma-separated layer numbers, e.g. 10,50,100"), err
    assert "MISSING" not in "\n".join(err[1:]) and not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv,verbose", [
    (["slice", "m.stl", "-o", "o", "-v"], True), (["-v", "slice", "m.stl", "-o", "o"], True),
    (["slice", "m.stl", "-o", "o"], False), (["export", "vplus", "-o", "o", "--verbose"], True),
    (["-v", "export", "vplus", "-o", "o"], True), (["cell", "check", "-v"], True),
    (["calibrate", "synthetic", "-o", "o", "-v"], True), (["tune", "-v", "--json"], True)])
def test_verbose_is_taken_before_and_after_the_command(argv, verbose):
    # a docs hunt's: 'icefab slice x -o y -v' was "unrecognized arguments: -v"
    from icefab.cli import build_parser

    assert build_parser().parse_args(argv).verbose is verbose


def test_every_listed_command_exists_and_none_is_skipped():
    """The command table names modules that exist; each registers its command (a missing
    or misspelled module used to be skipped silently)."""
    import argparse

    from icefab.cli import SUBCOMMANDS, build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert set(SUBCOMMANDS) <= set(sub.choices)
    cli_dir = Path(__file__).resolve().parents[1] / "src" / "icefab" / "cli"
    modules = {p.stem[:-4] for p in cli_dir.glob("*_cmd.py")}
    assert modules == set(SUBCOMMANDS), "a *_cmd.py module not in SUBCOMMANDS, or the reverse"


def test_one_build_time_comparison_in_words():
    """Issue 10: paths said 2.71 h, plan '-153.3 % reduction' against it, the demo '41 %
    less'. Now one comparison (both times a robot can run), said in words."""
    from icefab.cli.common import compare_build_times, hours

    assert hours(3 * 3600 + 360) == "3.10 h" and hours(90) == "1.5 min"
    faster = compare_build_times(3600.0, 7200.0)
    assert faster == ("minimum-time trajectories take 1.00 h, the same paths at constant "
                      "speed 2.00 h: minimum-time is 50 % shorter (2.00x as fast)")
    slower = compare_build_times(7200.0, 3600.0)
    assert slower.endswith("minimum-time is 100 % longer") and "-100" not in slower
    assert "no motion" in compare_build_times(0.0, 10.0)


def test_paths_and_simulate_take_the_parts_a_job_names(tmp_path, capsys):
    """`slice` and `build` took parts.files when no MODEL was given; `paths`, `plan` and
    `simulate` asked for one (a tester's legacy control file). A result file among mesh files was
    read as a mesh ('unknown mesh format'); it must be given alone."""
    import trimesh

    trimesh.creation.box(extents=(12.0, 10.0, 4.0)).export(tmp_path / "box.stl")
    job = tmp_path / "job.toml"
    job.write_text('[parts]\nfiles = ["box.stl"]\n[slicing]\nlayer_thickness_mm = 1.0\n'
                   "[simulation]\nlayers = 4\n")
    assert main(["paths", "-c", str(job), "-o", str(tmp_path / "p")]) == 0
    assert "part boundary" in capsys.readouterr().out
    assert (tmp_path / "p" / "toolpaths.npz").is_file()
    assert main(["plan", "-c", str(job), "-o", str(tmp_path / "t")]) == 0
    assert (tmp_path / "t" / "trajectories.npz").is_file()
    assert main(["simulate", "-c", str(job), "-o", str(tmp_path / "s")]) == 0
    assert (tmp_path / "s").is_dir()
    capsys.readouterr()
    for command in (["paths"], ["plan"], ["simulate"]):
        assert main(command + ["-o", str(tmp_path / "none")]) == 2
        assert "no input: give mesh file(s)" in capsys.readouterr().err
    stack = tmp_path / "p" / "toolpaths.npz"
    for command in (["paths", str(stack), str(tmp_path / "box.stl")],
                    ["plan", str(tmp_path / "box.stl"), str(stack)],
                    ["simulate", str(tmp_path / "box.stl"), "demo"]):
        assert main(command + ["-o", str(tmp_path / "two")]) == 2
        err = capsys.readouterr().err
        assert "give it alone" in err and "unknown mesh format" not in err, err
    assert not (tmp_path / "none").exists() and not (tmp_path / "two").exists()


def test_slice_paths_and_plan_take_demo(tmp_path, capsys):
    # the README: "slice, paths, plan, simulate and build take ... demo alone"; slice,
    # paths and plan read it as a file name ('demo: mesh file not found')
    from icefab.cli.common import placed_model
    from icefab.config import Job
    from icefab.demo import demo_mug
    from icefab.mesh import place_mesh
    from icefab.slicing import load_stack

    job = tmp_path / "job.toml"
    job.write_text("[slicing]\nlayer_thickness_mm = 2.0\n")
    assert main(["slice", "demo", "-c", str(job), "-o", str(tmp_path / "s")]) == 0
    assert "demo-mug: 4388 facets" in capsys.readouterr().out
    assert len(load_stack(tmp_path / "s" / "stack.npz")) == 62   # 125 mm in 2 mm layers
    for command in ("paths", "plan"):
        assert main([command, "demo", "-c", str(job), "-o", str(tmp_path / command)]) == 0
    assert (tmp_path / "plan" / "trajectories.npz").is_file()
    mesh, same = placed_model(["demo"], Job())
    assert same == Job() and mesh.vertices.tolist() == \
        place_mesh(demo_mug(), Job()).vertices.tolist()
    capsys.readouterr()
    # placed and checked by the job, as a file is
    far = tmp_path / "far.toml"
    far.write_text("[cell]\nee_origin_mm = [560.0, 0.0]\n")
    assert main(["slice", "demo", "-c", str(far), "-o", str(tmp_path / "far")]) == 2
    assert "beyond the reach" in capsys.readouterr().err
    assert not (tmp_path / "far").exists()


def test_negative_values_of_options_are_values():
    # a tester's '--zbase -1e9' and '--bounds -50,-50,50,50' were 'expected one argument'
    from icefab.cli import build_parser

    parser = build_parser()
    args = parser.parse_args(["export", "vplus", "--zbase", "-1e9", "--yaw", "-.5", "-o", "x"])
    assert (args.zbase, args.yaw, args.out) == (-1e9, -0.5, "x")
    args = parser.parse_args(["cell", "serve", "--state", "s", "--bounds", "-50,-50,50,50"])
    assert args.bounds == "-50,-50,50,50"
    args = parser.parse_args(["slice", "m.stl", "-c", "j.toml", "-o", "o"])   # options stay
    assert (args.job, args.out) == ("j.toml", "o")


@pytest.mark.parametrize("closed", [1, 2], ids=["stdout", "stderr"])
def test_a_command_started_with_a_standard_stream_closed_still_works(tmp_path, closed):
    """'>&-' gave Python no sys.stdout: the results were written, then an AttributeError
    ended the command with exit 1; '2>&-' failed at once with no message (hunt P)."""
    import os
    import subprocess
    import sys

    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "icefab", "slice", "demo", "-o", str(out)],
                          preexec_fn=lambda: os.close(closed), stdin=subprocess.DEVNULL,
                          timeout=300)
    assert proc.returncode == 0
    assert (out / "stack.npz").is_file()


def test_progress_on_a_full_stderr_lets_the_job_go_on():
    """'2>/dev/full': the first progress line's OSError ended the whole job (hunt P)."""
    import io

    from icefab.cli.common import Progress

    class Full(io.StringIO):
        tries = 0

        def write(self, s):
            Full.tries += 1
            raise OSError(28, "No space left on device")

    progress = Progress("paths", stream=Full(), interval_s=0.0)
    for k in range(1, 6):
        progress(k, 5)   # raises nothing
    assert Full.tries == 2   # the first line, then only the final one is tried again


@pytest.mark.parametrize("exc, code, said", [("Terminated", 143, "icefab: terminated"),
                                             ("KeyboardInterrupt", 130, "icefab: interrupted")])
def test_a_signal_while_the_options_are_read_is_one_line(monkeypatch, capsys, exc, code, said):
    """SIGTERM in a command's first second (its options read, its modules imported) ended
    in a Terminated traceback and exit 1 (a hunt's); Ctrl-C there likewise."""
    import icefab.cli as cli
    from icefab.cli.common import Terminated

    def stopped():
        raise Terminated() if exc == "Terminated" else KeyboardInterrupt()

    monkeypatch.setattr(cli, "build_parser", stopped)
    assert cli.main(["demo"]) == code
    err = capsys.readouterr().err
    assert err.strip() == said


@pytest.mark.parametrize("wrapper", [SystemError, RuntimeError, ImportError])
@pytest.mark.parametrize("exc, code, said", [("Terminated", 143, "icefab slice: terminated"),
                                             ("KeyboardInterrupt", 130,
                                              "icefab slice: interrupted")])
def test_a_signal_as_numba_loads_a_kernel_is_one_line(monkeypatch, capsys, tmp_path, exc,
                                                      code, said, wrapper):
    """A signal while numba's dispatcher ran Python code (loading a cached kernel) came out
    as "SystemError: CPUDispatcher(...) returned a result with an exception set", with a
    traceback and exit 1 (a hunt's); CPython chains the signal's exception as its cause.
    Another SystemError stays an error."""
    import icefab.cli as cli
    import icefab.cli.slice_cmd as slice_cmd
    from icefab.cli.common import Terminated

    def interrupted(args):
        try:
            raise Terminated() if exc == "Terminated" else KeyboardInterrupt()
        except KeyboardInterrupt as e:
            # numba's dispatcher (SystemError), a class's __set_name__ (RuntimeError),
            # matplotlib's first import (ImportError)
            raise wrapper("CPUDispatcher(<function _filter_compact>) returned a result "
                          "with an exception set") from e

    monkeypatch.setattr(slice_cmd, "run", interrupted)
    assert cli.main(["slice", "demo", "-o", str(tmp_path / "s")]) == code
    assert capsys.readouterr().err.strip() == said

    def broken(args):
        raise wrapper("something else")

    monkeypatch.setattr(slice_cmd, "run", broken)
    with pytest.raises(wrapper, match="something else"):
        cli.main(["slice", "demo", "-o", str(tmp_path / "s")])


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_a_sigterm_lost_in_a_weakref_callback_stops_the_command_at_its_next_progress(
        monkeypatch, capsys, tmp_path):
    """A SIGTERM handler's exception raised inside a weakref callback (Python's import
    locks have one) is printed as "Exception ignored" and lost: a build stopped at once
    planned on, and 'icefab build --stop' gave up after 60 s (CI stop 48). The command's
    next progress report raises it again."""
    import gc
    import os
    import signal
    import weakref

    import icefab.cli as cli
    import icefab.cli.common as common
    import icefab.cli.slice_cmd as slice_cmd

    monkeypatch.setattr(common, "_TERMINATED", [False])
    reported = []

    def run(args):
        class Lock:
            pass

        def callback(ref):
            os.kill(os.getpid(), signal.SIGTERM)   # its handler runs in here
            sum(range(1000))

        lock = Lock()
        ref = weakref.ref(lock, callback)
        del lock
        gc.collect()
        assert ref() is None
        reported.append("went on")       # the Terminated was lost
        common.Progress("slicing", interval_s=0.0)(1, 2)
        reported.append("not stopped")
        return 0

    monkeypatch.setattr(slice_cmd, "run", run)
    assert cli.main(["slice", "demo", "-o", str(tmp_path / "s")]) == 143
    err = capsys.readouterr().err
    assert reported == ["went on"]
    assert err.strip().endswith("icefab slice: terminated")
    # the next command, here on another thread, starts without it (a check's: it stopped)
    import threading

    def run_again(args):
        common.Progress("slicing", interval_s=0.0)(1, 2)
        reported.append("ran")
        return 0

    monkeypatch.setattr(slice_cmd, "run", run_again)
    got = []
    worker = threading.Thread(target=lambda: got.append(
        cli.main(["slice", "demo", "-o", str(tmp_path / "t")])))
    worker.start()
    worker.join()
    assert got == [0] and reported[-1] == "ran"


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_a_sigterm_lost_after_the_last_progress_ends_the_command_as_terminated(
        monkeypatch, capsys, tmp_path):
    """A SIGTERM lost (in a weakref callback) after a command's last progress report, or
    in a command that reports none, let it end with 0 as if no stop had been asked for:
    it ends as terminated (143), its work done."""
    import gc
    import os
    import signal
    import weakref

    import icefab.cli as cli
    import icefab.cli.common as common
    import icefab.cli.slice_cmd as slice_cmd

    monkeypatch.setattr(common, "_TERMINATED", [False])

    def run(args):
        class Lock:
            pass

        lock = Lock()
        ref = weakref.ref(lock, lambda r: os.kill(os.getpid(), signal.SIGTERM))
        del lock
        gc.collect()
        assert ref() is None
        return 0

    monkeypatch.setattr(slice_cmd, "run", run)
    assert cli.main(["slice", "demo", "-o", str(tmp_path / "s")]) == 143
    assert capsys.readouterr().err.strip().endswith("icefab slice: terminated")
    monkeypatch.setattr(slice_cmd, "run", lambda args: 0)   # and without one: 0
    assert cli.main(["slice", "demo", "-o", str(tmp_path / "t")]) == 0


@pytest.mark.parametrize("wrapped", [False, True])
def test_ctrl_c_while_the_command_loads_is_one_line(monkeypatch, capsys, wrapped):
    """Ctrl-C in the command's first half second (numpy, scipy, numba loading) was a
    KeyboardInterrupt traceback out of an import (hunts'): the 'icefab' entry point
    (icefab.__main__.run) loads the command's modules itself and says it in one line."""
    import importlib.abc
    import sys

    from icefab.__main__ import run

    class Interrupted(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path, target=None):
            if name == "icefab.cli":
                if wrapped:     # as a class's __set_name__ wraps it
                    try:
                        raise KeyboardInterrupt
                    except KeyboardInterrupt as e:
                        raise RuntimeError("Error calling __set_name__") from e
                raise KeyboardInterrupt
            return None

    monkeypatch.delitem(sys.modules, "icefab.cli")
    monkeypatch.setattr(sys, "meta_path", [Interrupted(), *sys.meta_path])
    with pytest.raises(SystemExit) as stop:
        run()
    assert stop.value.code == 130
    assert capsys.readouterr().err == "icefab: interrupted\n"


def test_importing_icefab_loads_no_numpy():
    # what the entry point's own guard needs: the package itself loads in milliseconds
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", "import icefab, sys; "
                        "print(sorted(m for m in ('numpy', 'scipy', 'numba') "
                        "if m in sys.modules))"], capture_output=True, text=True, check=True)
    assert r.stdout.strip() == "[]"
    r = subprocess.run([sys.executable, "-c", "from icefab import Job, Region, load_mesh; "
                        "print(Job().motion.dt_s)"], capture_output=True, text=True,
                       check=True)
    assert r.stdout.strip() == "0.016"
