"""The README's promises: its Python snippet runs, its set-up commands are the ones CI uses."""
import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def test_python_snippets_run():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert blocks
    for block in blocks:
        exec(compile(block, "README.md", "exec"), {})


def test_ci_runs_the_readme_test_command():
    text = README.read_text()
    setup = text.split("## Set up", 1)[1].split("##", 1)[0]
    commands = [line.strip() for line in setup.splitlines() if line.startswith("    ")]
    assert len(commands) == 2, commands
    ci = (README.parent / ".ci" / "run").read_text()
    pytest_cmd = commands[1].split("&&")[1].strip()
    assert pytest_cmd in ci
