"""The package's layers (README, "Layout"): every import of one quasisim module by another, at the top of a
file, inside a function or under ``TYPE_CHECKING``, goes to a lower or the same layer, and no modules import
each other in a circle. Read from the source (ast), so it costs nothing."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "quasisim"

# low to high; a module may import its own package and the layers below it
LAYERS: tuple[tuple[str, ...], ...] = (
    ("quasisim", "errors", "files", "config", "rotations", "keypoints", "limits", "tracecache", "runtime"),
    ("assets",),  # robot hand and object models (MJCF, meshes, SDFs)
    ("data",),  # the demo format and its converters
    ("sim",),  # the differentiable quasi-physical simulator
    ("optim",),  # trajectories, objectives, Adam, system identification
    ("targets",),  # MuJoCo and PyBullet, the scene, perturbed worlds
    ("method",),  # retargeting, the stages, the tracker
    ("eval",),  # metrics, robust success, reports, tables, exports
    ("envs",),  # the Gymnasium tracking environment
    ("policy",),  # learned tracking policies (PPO): training, evaluation, learning curves
    ("pipeline",),  # one demo end to end
    ("batch", "raycluster"),  # many demos on Ray; which Ray, and clusters of our own
    ("bench",),  # benchmarks
    ("cli",),  # the command line
)
RANK = {name: i for i, names in enumerate(LAYERS) for name in names}


def _modules() -> dict[str, Path]:
    out = {}
    for p in SRC.rglob("*.py"):
        parts = p.relative_to(SRC.parent).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return out


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The quasisim modules ``name`` imports anywhere in its file (the longest module prefix of each name)."""
    found: set[str] = set()
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*up, *([node.module] if node.module else [])])
            names = [base, *(f"{base}.{a.name}" for a in node.names)]
        else:
            continue
        for n in names:
            while n and n not in modules:
                n = n.rpartition(".")[0]
            if n and n != name:
                found.add(n)
    return found


def _layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "quasisim"


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {m: _imports(m, p, modules) for m, p in modules.items()}


def test_every_module_has_a_layer() -> None:
    missing = sorted({_layer(m) for m in _modules()} - set(RANK))
    assert not missing, f"packages or modules with no layer in LAYERS: {missing}"


def test_no_import_runs_up_the_layers() -> None:
    up = [
        f"{m} -> {n}"
        for m, deps in _graph().items()
        for n in sorted(deps)
        if RANK.get(_layer(n), -1) > RANK.get(_layer(m), -1)
    ]
    assert not up, "imports that run up the layers:\n" + "\n".join(sorted(up))


def test_no_modules_import_each_other_in_a_circle() -> None:
    graph = _graph()
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    circles: list[list[str]] = []

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                circles.append([*path[path.index(n) :], n])
            elif n not in state:
                visit(n, [*path, n])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not circles, "import circles:\n" + "\n".join(" -> ".join(c) for c in circles)
