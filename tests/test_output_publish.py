"""Publishing results into OUT: all or nothing as the user sees it, errors naming the
user's path, one command at a time, no collisions between commands, stale temporaries of
killed runs removed, and durable atomic writes (issue 10, "Outputs")."""
from __future__ import annotations

import importlib
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from icefab.cli import common
from icefab.cli.common import output_dir, remove_stale_temporaries
from icefab.errors import OutputError


def _tree(root: Path) -> dict[str, object]:
    """Everything under root: name -> bytes (files), link target (symlinks), None (dirs)."""
    out: dict[str, object] = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        if p.is_symlink():
            out[rel] = ("link", os.readlink(p))
        elif p.is_dir():
            out[rel] = None
        else:
            out[rel] = p.read_bytes()
    return out


def _first_run(out: Path) -> None:
    with output_dir(out, "slice") as d:
        (d / "stack.npz").write_text("stack 1")
        (d / "layers.png").write_text("picture 1")
        (d / "layer_0000").mkdir()
        (d / "layer_0000" / "p.bin").write_text("program 1")


def _second_run(out: Path) -> None:
    with output_dir(out, "slice") as d:
        (d / "stack.npz").write_text("stack 2")
        (d / "layers.png").write_text("picture 2")
        (d / "layer_0000").mkdir()
        (d / "layer_0000" / "p.bin").write_text("program 2")


@pytest.mark.parametrize("obstacle", ["folder-for-file", "file-for-folder", "symlink-file",
                                      "symlink-folder"])
def test_an_obstacle_is_one_error_naming_the_users_path_and_nothing_changes(tmp_path,
                                                                             obstacle):
    out = tmp_path / "out"
    _first_run(out)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "keep").write_text("not icefab's")
    name = {"folder-for-file": "layers.png", "file-for-folder": "layer_0000",
            "symlink-file": "stack.npz", "symlink-folder": "layer_0000"}[obstacle]
    target = out / name
    if target.is_dir():
        for f in target.iterdir():
            f.unlink()
        target.rmdir()
    else:
        target.unlink()
    if obstacle == "folder-for-file":
        target.mkdir()
        (target / "mine.txt").write_text("user's")
    elif obstacle == "file-for-folder":
        target.write_text("user's file")
    else:
        target.symlink_to(elsewhere)
    before, outside = _tree(out), _tree(elsewhere)
    with pytest.raises(OutputError) as info:
        _second_run(out)
    message = str(info.value)
    assert message.startswith(f"{target}: is "), message
    assert "\n" not in message and ".icefab-" not in message
    assert _tree(out) == before and _tree(elsewhere) == outside
    assert sorted(p.name for p in tmp_path.iterdir()) == ["elsewhere", "out"]


@pytest.mark.parametrize("fail_at", [0, 1, 2, 3])
def test_a_failing_rename_rolls_everything_back(tmp_path, monkeypatch, fail_at):
    """Fail the n-th rename of the publish (fail_at 3 = the record, swapped last): OUT is
    exactly as before, the error names OUT's entry, nothing temporary is left."""
    out = tmp_path / "out"
    _first_run(out)
    (out / "users-own.txt").write_text("mine")
    before = _tree(out)
    real = os.rename
    calls = []

    def rename(src, dst):
        if Path(src).parent.name.startswith(".out.icefab-"):  # moving a new result in
            calls.append(Path(dst).name)
            if len(calls) == fail_at + 1:
                raise PermissionError(13, "Permission denied")
        return real(src, dst)

    monkeypatch.setattr(os, "rename", rename)
    with pytest.raises(OutputError, match=rf"^{out}/[^ ]+: cannot put the result in place "
                                          rf"\(Permission denied\); {out} is as it was$"):
        _second_run(out)
    assert calls[-1] == (["layer_0000", "layers.png", "stack.npz", ".icefab-slice"][fail_at])
    assert _tree(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_while_the_results_move_leaves_out_old_or_new_never_half(
        tmp_path, monkeypatch, signum):
    """Ctrl-C or SIGTERM right after the first old entry is moved aside (a hunt's strace
    injection): the signal waits until the moves are done, then the run is interrupted
    and OUT is as before; nothing temporary is left (the old programs had stayed only in
    a backup, which the next command removed)."""
    from icefab import cli

    out = tmp_path / "out"
    _first_run(out)
    before = _tree(out)
    real = os.rename
    sent = []

    def rename(src, dst):
        got = real(src, dst)
        if Path(dst).parent.name.startswith(".icefab-backup-") and not sent:
            sent.append(Path(src).name)
            os.kill(os.getpid(), signum)
        return got

    monkeypatch.setattr(os, "rename", rename)
    cli._on_sigterm.pid = os.getpid()
    old = signal.signal(signal.SIGTERM, cli._on_sigterm)
    try:
        with pytest.raises(KeyboardInterrupt):
            _second_run(out)
    finally:
        signal.signal(signal.SIGTERM, old)
    assert sent and _tree(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_sigterm_ends_a_command_as_ctrl_c_does(tmp_path, monkeypatch, capsys):
    """SIGTERM to a command: its temporary result folder goes, one line, exit 143."""
    from icefab import cli
    from icefab.cli import slice_cmd

    def run(args):
        with output_dir(args.out, "slice") as d:
            (d / "stack.npz").write_text("half")
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)

    monkeypatch.setattr(slice_cmd, "run", run)
    before = signal.getsignal(signal.SIGTERM)
    assert cli.main(["slice", "demo", "-o", str(tmp_path / "out")]) == 143
    assert capsys.readouterr().err == "icefab slice: terminated\n"
    assert list(tmp_path.iterdir()) == []
    assert signal.getsignal(signal.SIGTERM) is before


def test_the_record_is_swapped_in_last(tmp_path, monkeypatch):
    out = tmp_path / "out"
    _first_run(out)
    order = []
    real = os.rename

    def rename(src, dst):
        order.append(Path(dst).name)
        return real(src, dst)

    monkeypatch.setattr(os, "rename", rename)
    _second_run(out)
    into_out = [n for n in order if n in ("layer_0000", "layers.png", "stack.npz",
                                          ".icefab-slice")]
    assert into_out[-1] == ".icefab-slice"
    assert (out / "stack.npz").read_text() == "stack 2"
    assert (out / "layer_0000" / "p.bin").read_text() == "program 2"


def test_two_commands_never_overwrite_each_others_files(tmp_path):
    out = tmp_path / "out"
    with output_dir(out, "plan") as d:
        (d / "plan-summary.txt").write_text("plan")
        (d / "shared-name.txt").write_text("plan's")
    with pytest.raises(OutputError, match=rf"^{out}/shared-name.txt: written there by "
                                          r"'icefab plan', which this command would "
                                          r"overwrite; write into another folder \(-o\)$"):
        with output_dir(out, "valves") as d:
            (d / "valves-summary.txt").write_text("valves")
            (d / "shared-name.txt").write_text("valves'")
    assert (out / "shared-name.txt").read_text() == "plan's"
    assert not (out / "valves-summary.txt").exists()


def test_cli_commands_write_distinct_names_into_one_folder(tmp_path):
    """plan then valves into the folder plan wrote (the issue's reproducer): both
    summaries stay, each command's record lists only its own files."""
    from icefab.cli import main

    out = tmp_path / "out"
    job = tmp_path / "job.toml"
    job.write_text("[slicing]\nlayer_thickness_mm = 8.0\n[cell]\ncpus = 1\n"
                   "[flow]\nout_of_range = \"clamp\"\n")
    from icefab.demo import demo_mug
    from icefab.mesh import write_stl

    write_stl(demo_mug(), tmp_path / "mug.stl")
    assert main(["paths", str(tmp_path / "mug.stl"), "-c", str(job), "-o", str(out)]) == 0
    assert main(["plan", str(out / "toolpaths.npz"), "-c", str(job), "-o", str(out)]) == 0
    assert main(["valves", str(out / "trajectories.npz"), "-c", str(job), "-o",
                 str(out)]) == 0
    records = {r.name: set(r.read_text().split()) for r in out.glob(".icefab-*")}
    assert set(records) == {".icefab-paths", ".icefab-plan", ".icefab-valves"}
    names = [n for r in records.values() for n in r]
    assert len(names) == len(set(names)), records
    for r in records.values():
        for n in r:
            assert (out / n).exists()


def test_concurrent_publishes_do_not_interleave(tmp_path, monkeypatch, capfd):
    """While one command holds OUT's lock, another waits (saying so) and then publishes
    its complete set on top; a slowed rename cannot mix two runs' files."""
    out = tmp_path / "out"
    _first_run(out)
    done = threading.Event()

    def second():
        _second_run(out)
        done.set()

    with common._locked(out.parent, out):
        t = threading.Thread(target=second)
        t.start()
        time.sleep(1.0)
        assert not done.is_set()
        assert (out / "stack.npz").read_text() == "stack 1"
    t.join(30)
    assert done.is_set()
    assert "waiting for another icefab command writing into" in capfd.readouterr().err
    assert (out / "stack.npz").read_text() == "stack 2"
    assert (out / "layers.png").read_text() == "picture 2"


def test_stale_temporaries_of_dead_runs_are_removed(tmp_path):
    out = tmp_path / "out"
    _first_run(out)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True).stdout.strip()
    stale = tmp_path / f".out.icefab-{dead}.0123abcd"
    alive = tmp_path / f".out.icefab-{os.getppid()}.0123abcd"
    legacy_old, legacy_new = tmp_path / ".out.abc_1234", tmp_path / ".out.xyz_9876"
    backup = out / f".icefab-backup-{dead}.89abcdef"
    other = tmp_path / ".other.icefab-1.0123abcd"  # another output folder's: not ours
    for p in (stale, alive, legacy_old, legacy_new, backup, other):
        p.mkdir()
        (p / "stack.npz").write_text("x")
    long_ago = time.time() - 2 * common.LEGACY_TEMP_AGE_S
    os.utime(legacy_old, (long_ago, long_ago))
    removed = remove_stale_temporaries(out)
    assert sorted(removed) == sorted([stale, legacy_old, backup])
    for p in (alive, legacy_new, other):
        assert p.exists()


def test_a_killed_command_leaves_nothing_the_next_run_keeps(tmp_path):
    out = tmp_path / "out"
    code = ("import sys, time\nfrom icefab.cli.common import output_dir\n"
            f"with output_dir({str(out)!r}, 'slice') as d:\n"
            "    (d / 'stack.npz').write_text('half')\n"
            "    print('ready', flush=True)\n    time.sleep(60)\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    left = [p.name for p in tmp_path.iterdir()]
    assert len(left) == 1 and left[0].startswith(".out.icefab-")
    _first_run(out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


# ---------------------------------------------------------------------- atomic.py


def test_importing_atomic_neither_reads_nor_changes_the_umask(monkeypatch, tmp_path):
    import icefab.atomic

    def forbidden(*_):
        raise AssertionError("os.umask called")

    monkeypatch.setattr(os, "umask", forbidden)
    atomic = importlib.reload(icefab.atomic)
    atomic.write_atomic(tmp_path / "f.txt", "x")
    with output_dir(tmp_path / "out", "test") as d:
        (d / "a.txt").write_text("a")
    monkeypatch.undo()
    importlib.reload(icefab.atomic)


def test_results_get_the_umask_modes(tmp_path):
    from icefab.atomic import write_atomic

    old = os.umask(0o027)
    try:
        write_atomic(tmp_path / "f.txt", "x")
        with output_dir(tmp_path / "out", "test") as d:
            (d / "a.txt").write_text("a")
    finally:
        os.umask(old)
    assert (tmp_path / "f.txt").stat().st_mode & 0o777 == 0o640
    assert (tmp_path / "out").stat().st_mode & 0o777 == 0o750


def test_atomic_write_fsyncs_the_data_before_the_rename_and_the_folder_after(tmp_path,
                                                                             monkeypatch):
    from icefab import atomic

    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        return real_fsync(fd)

    def replace(src, dst):
        events.append(("replace", str(dst)))
        return real_replace(src, dst)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    target = tmp_path / "result.npz"
    atomic.write_atomic(target, b"data")
    kinds = [e[0] for e in events]
    at = kinds.index("replace")
    assert events[at] == ("replace", str(target))
    assert any(k == "fsync" and Path(p).name.startswith(".result.npz.")
               for k, p in events[:at])                      # the data, before
    assert ("fsync", str(tmp_path)) in events[at + 1:]         # the folder, after


def test_paths_writes_its_file_beside_the_picture_and_nothing_when_the_picture_fails(
        tmp_path, monkeypatch):
    """``icefab paths`` writes the toolpath file on a thread while it draws: a picture
    that fails leaves OUT as it was (the file thread is waited for, then all is dropped);
    one that works leaves the file whole (it loads)."""
    from icefab.cli import main, paths_cmd
    from icefab.demo import demo_mug
    from icefab.mesh import write_stl
    from icefab.paths import load_toolpaths

    job = tmp_path / "job.toml"
    job.write_text("[slicing]\nlayer_thickness_mm = 8.0\n[cell]\ncpus = 1\n")
    write_stl(demo_mug(), tmp_path / "mug.stl")
    out = tmp_path / "out"

    def broken(*_a, **_k):
        raise RuntimeError("no picture")
    monkeypatch.setattr(paths_cmd, "plot_toolpaths", broken)
    with pytest.raises(RuntimeError, match="no picture"):
        paths_cmd.run(paths_cmd_args(tmp_path / "mug.stl", job, out))
    assert not out.exists() or not any(out.iterdir())
    monkeypatch.undo()
    assert main(["paths", str(tmp_path / "mug.stl"), "-c", str(job), "-o", str(out)]) == 0
    assert len(load_toolpaths(out / "toolpaths.npz").layers) > 0
    assert (out / "paths.png").stat().st_size > 0


def paths_cmd_args(model: Path, job: Path, out: Path):
    from icefab.cli import build_parser
    return build_parser().parse_args(["paths", str(model), "-c", str(job), "-o", str(out)])


def test_an_empty_or_symlinked_output_folder_is_refused_before_any_work(tmp_path, monkeypatch,
                                                                         capsys):
    """-o '' wrote into the current folder, and a symbolic link to a folder was refused
    only when the results were put in place, as "not a folder" (hunt P)."""
    from icefab import cli

    monkeypatch.chdir(tmp_path)
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")
    assert cli.main(["slice", "demo", "-o", ""]) == 2
    assert capsys.readouterr().err == "icefab slice: error: -o '': an empty folder name\n"
    assert cli.main(["slice", "demo", "-o", "link"]) == 2
    assert capsys.readouterr().err == (f"icefab slice: error: -o link: is a symbolic link; "
                                       f"give the folder it points to ({tmp_path / 'real'})\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link", "real"]
    assert list((tmp_path / "real").iterdir()) == []


def test_an_output_folder_with_a_long_name_gets_its_results(tmp_path):
    """A valid 240-character folder name was refused: its temporary sibling's name (the
    name, '.icefab-', the process and 8 characters) was too long (hunt P)."""
    out = tmp_path / ("a" * 240)
    out.mkdir()
    _first_run(out)
    assert (out / "stack.npz").read_text() == "stack 1"
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name]


def test_a_folder_it_cannot_write_into_is_refused_before_any_work(tmp_path, monkeypatch,
                                                                  capsys):
    """A read-only output folder was found only after the whole job (hunt P)."""
    from icefab import cli
    from icefab.cli import slice_cmd

    ro = tmp_path / "ro"
    ro.mkdir()
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: Path(p) != ro and real(p, mode))
    monkeypatch.setattr(slice_cmd, "run", lambda args: pytest.fail("worked"))
    assert cli.main(["slice", "demo", "-o", str(ro / "out")]) == 2
    assert capsys.readouterr().err == (f"icefab slice: error: -o {ro / 'out'}: cannot write "
                                       f"into {ro} (permission denied)\n")
    assert cli.main(["slice", "demo", "-o", str(ro)]) == 2


_COMMANDS = {"slice": ["demo"], "paths": ["demo"], "plan": ["demo"], "valves": ["t.npz"],
             "simulate": ["demo"], "export": ["gcode", "t.npz"], "tune": [], "demo": []}


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc")
@pytest.mark.parametrize("command", sorted(_COMMANDS))
def test_an_output_folder_where_nothing_can_be_made_is_refused_before_any_work(
        command, monkeypatch, capsys):
    """'-o /proc/x' passed the permission check (root may write anywhere, as os.access
    sees it) and 'icefab slice' refused it only after slicing the whole mesh (a review's):
    one line, exit 2, before the command's own work."""
    from icefab import cli

    module = importlib.import_module(f"icefab.cli.{command}_cmd")
    for name in ("run", "run_gcode"):
        if hasattr(module, name):
            monkeypatch.setattr(module, name, lambda args: pytest.fail("worked"))
    argv = [command, *_COMMANDS[command], "-o", "/proc/x/out"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"icefab {command}: error: -o /proc/x/out: cannot write into /proc (")
    assert err.count("\n") == 1


def test_a_read_only_file_system_is_refused_before_any_work_even_for_root(tmp_path,
                                                                          monkeypatch, capsys):
    """A read-only mount passes os.access for root in some set-ups (and /proc always):
    the folder is tried by making one there, and the system's reason is given."""
    import errno

    from icefab import cli
    from icefab.cli import slice_cmd

    ro = tmp_path / "ro"
    ro.mkdir()
    real = os.mkdir

    def mkdir(p, *a, **kw):
        if Path(p).parent == ro:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(p))
        return real(p, *a, **kw)

    monkeypatch.setattr(os, "mkdir", mkdir)
    monkeypatch.setattr(slice_cmd, "run", lambda args: pytest.fail("worked"))
    assert cli.main(["slice", "demo", "-o", str(ro / "out")]) == 2
    assert capsys.readouterr().err == (f"icefab slice: error: -o {ro / 'out'}: cannot write "
                                       f"into {ro} (Read-only file system)\n")
    assert list(ro.iterdir()) == []
    monkeypatch.setattr(os, "mkdir", real)
    with output_dir(ro / "out", "slice") as d:   # a folder that takes one is left as it was
        (d / "stack.npz").write_text("stack")
    assert sorted(p.name for p in ro.iterdir()) == ["out"]
