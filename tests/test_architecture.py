"""The import graph of icefab follows the pipeline (ARCHITECTURE.md): no cycle, and no
module imports a later stage. Read from the source with ``ast`` (nothing is imported), so
function-local imports count too; ``if TYPE_CHECKING:`` imports count for the direction
(an annotation naming a later stage is a back-edge too) but not for cycles (they never run).

A new module must be placed in STAGES (the one declaration of the stage order): the test
says which one is missing.
"""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"

#: The pipeline, bottom first. A module may import its own stage and earlier ones. An entry
#: names a module or a package (then every module inside it belongs to the stage too).
STAGES: list[tuple[str, tuple[str, ...]]] = [
    ("foundation", ("icefab._kernel_cache", "icefab.errors", "icefab.atomic", "icefab.config",
                    "icefab.core", "icefab.types", "icefab.stages", "icefab.parallel",
                    "icefab.frames", "icefab.robots", "icefab._codec", "icefab.resultfiles",
                    "icefab.inputs", "icefab.workload")),
    ("geometry", ("icefab._smooth", "icefab.geometry")),
    ("mesh", ("icefab.mesh", "icefab.demo")),
    ("slicing", ("icefab.adaptive", "icefab.fitting", "icefab.slicing")),
    ("ruled", ("icefab.ruled",)),
    ("regions", ("icefab.regions",)),
    ("paths", ("icefab._tour", "icefab.paths")),
    ("motion", ("icefab._mtts", "icefab.motion")),
    ("feedback", ("icefab.feedback",)),
    ("flow", ("icefab._pulses", "icefab.flow", "icefab.headroom", "icefab.findings")),
    ("sim", ("icefab.sim",)),
    ("report", ("icefab.report",)),
    ("export", ("icefab.export",)),
    ("cell", ("icefab.cell",)),
    ("calibration", ("icefab.calibration",)),
    ("build", ("icefab.journal", "icefab.runcell", "icefab.linkedcell", "icefab.build")),
    ("cli", ("icefab.cli", "icefab.__main__", "icefab")),
]


def _modules() -> dict[str, Path]:
    out = {}
    for p in sorted((SRC / "icefab").rglob("*.py")):
        parts = list(p.relative_to(SRC).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


MODULES = _modules()


def _stage_of(module: str) -> int | None:
    best, rank = None, -1
    for k, (_, names) in enumerate(STAGES):
        for name in names:
            hit = module == name or (name != "icefab" and module.startswith(name + "."))
            if hit and len(name) > rank:
                best, rank = k, len(name)
    return best


def _imports(module: str, path: Path) -> list[tuple[str, bool, int]]:
    """(imported icefab module, inside ``if TYPE_CHECKING``, line) for every import."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    typing_only: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            typing_only.update(id(n) for n in ast.walk(node))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            for a in node.names:
                sub = f"{base}.{a.name}"
                targets.append(sub if sub in MODULES else base)
        for t in targets:
            while t and t not in MODULES and "." in t:
                t = t.rpartition(".")[0]
            if t in MODULES and t != module:
                out.append((t, id(node) in typing_only, node.lineno))
    return out


GRAPH = {m: _imports(m, p) for m, p in MODULES.items()}


def test_every_module_has_a_stage():
    missing = [m for m in MODULES if _stage_of(m) is None]
    assert not missing, (f"modules without a pipeline stage: {missing}; add each to STAGES "
                         "in tests/test_architecture.py and a line to ARCHITECTURE.md")


def test_no_import_from_a_later_stage():
    bad = []
    for m, edges in GRAPH.items():
        sm = _stage_of(m)
        for t, _, line in edges:
            st = _stage_of(t)
            if sm is not None and st is not None and st > sm:
                bad.append(f"{MODULES[m].relative_to(SRC)}:{line}: {m} ({STAGES[sm][0]}) "
                           f"imports {t} ({STAGES[st][0]}), a later stage")
    assert not bad, "\n".join(bad)


def test_no_import_cycle():
    runtime = {m: sorted({t for t, typing_only, _ in e if not typing_only})
               for m, e in GRAPH.items()}
    state: dict[str, int] = {}  # 1 on the stack, 2 done
    stack: list[str] = []
    cycles = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for t in runtime[m]:
            if state.get(t) == 1:
                cycles.append(stack[stack.index(t):] + [t])
            elif t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in sorted(runtime):
        if m not in state:
            visit(m)
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_the_graph_sees_imports():
    # the reader must find what is there (absolute, relative, package and function-local
    # imports), or the tests above would prove nothing
    def targets(m):
        return {t for t, _, _ in GRAPH[m]}

    assert {"icefab.core", "icefab.geometry", "icefab.regions"} <= targets("icefab.paths")
    assert {"icefab.mesh.obj", "icefab.mesh.topology"} <= targets("icefab.mesh.load")
    assert "icefab.flow" in targets("icefab.sim.plans")
    assert "icefab.slicing" in targets("icefab.cli.slice_cmd")  # inside run()
