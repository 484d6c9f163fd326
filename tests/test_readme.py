"""The README's promises: its Python snippet runs, its set-up commands are the ones CI uses."""
import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_python_snippets_run():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert blocks
    for block in blocks:
        exec(compile(block, "README.md", "exec"), {})


def test_toml_jobs_load(tmp_path):
    """Every job the README shows is one icefab reads; the gantry's is a gantry's (its
    settings were nowhere but config.py)."""
    import icefab

    blocks = re.findall(r"```toml\n(.*?)```", README.read_text(), re.S)
    jobs = []
    for i, block in enumerate(blocks):
        (tmp_path / f"{i}.toml").write_text(block, encoding="utf-8")
        jobs.append(icefab.load_job(tmp_path / f"{i}.toml"))
    gantry = [j for j in jobs if j.cell.robot == "gantry"]
    assert len(gantry) == 1 and not gantry[0].feedback.enabled
    assert gantry[0].flow.mode == "pwm" and gantry[0].cell.ee_origin_mm == (150.0, 150.0)


def test_ci_runs_the_readme_test_command():
    text = README.read_text()
    setup = text.split("## Set up", 1)[1].split("##", 1)[0]
    commands = [line.strip() for line in setup.splitlines() if line.startswith("    ")]
    assert len(commands) == 2, commands
    ci = (README.parent / ".ci" / "run").read_text()
    steps = [c.strip() for c in commands[1].split("&&")]
    # CI runs each step of the README's test command, in the same order
    at = [ci.find(step) for step in steps]
    assert -1 not in at and at == sorted(at), (steps, ci)


def test_set_up_commands_use_a_virtual_environment_and_state_the_python_version():
    import tomllib

    text = README.read_text()
    setup = text.split("## Set up", 1)[1].split("##", 1)[0]
    commands = [line.strip() for line in setup.splitlines() if line.startswith("    ")]
    for command in commands:
        assert command.startswith("python3 -m venv .venv && . .venv/bin/activate && "), command
    pyproject = tomllib.loads((README.parent / "pyproject.toml").read_text())
    needed = pyproject["project"]["requires-python"].removeprefix(">=")
    assert f"Python {needed} or newer" in setup


def test_the_demo_output_and_the_virtual_environment_are_ignored_by_git():
    import subprocess

    repo = README.parent
    if not (repo / ".git").exists():
        import pytest

        pytest.skip("not a git checkout: git's ignore rules cannot be asked")
    for path in ("icefab-demo/summary.txt", ".venv/bin/python3"):
        res = subprocess.run(["git", "-C", str(repo), "check-ignore", "-q", path])
        assert res.returncode == 0, f"{path} is not ignored by git"
