"""The layers import only downwards: ``envs`` and ``lcrl`` at the bottom, then
``captioner``, then ``train``. Every import statement counts, at module level or inside a
function; the one documented exception is ``lcrl.load`` (and its type hint), which reaches
up into ``train.policies.policy`` when it is called."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
#: Layer of each package: a package may import its own layer's package and lower layers.
LAYERS = {"envs": 0, "lcrl": 0, "captioner": 1, "train": 2}
#: The bottom packages stand beside each other: neither imports the other, except the one
#: shared module of user-facing errors.
SHARED = {"lcrl.errors"}
#: (file, imported module): the documented upward imports.
ALLOWED = {("lcrl/__init__.py", "train.policies.policy")}


def imports_of(source: str, package: str) -> list[tuple[int, str]]:
    """``(line, module)`` of every import statement in ``source`` (any depth), with
    relative imports resolved against ``package``."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                out.append((node.lineno, package + (f".{node.module}" if node.module else "")))
            elif node.module:
                out.append((node.lineno, node.module))
    return out


def violations(source: str, package: str, path: str) -> list[str]:
    """The imports of ``source`` (a file of ``package``) that break the layering."""
    bad = []
    for line, module in imports_of(source, package):
        top = module.split(".")[0]
        if top not in LAYERS or top == package or (path, module) in ALLOWED:
            continue
        if LAYERS[top] > LAYERS[package]:
            bad.append(f"{path}:{line} imports {module} (a layer above {package})")
        elif LAYERS[top] == LAYERS[package] and module not in SHARED:
            bad.append(f"{path}:{line} imports {module} (beside {package}, not below)")
    return bad


def test_no_import_points_up_the_layers():
    bad = []
    files = 0
    for package in LAYERS:
        for path in sorted((ROOT / package).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            bad += violations(path.read_text(), package, rel)
            files += 1
    assert files > 40  # the walk found the packages
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize(
    ("package", "source", "flagged"),
    [
        ("captioner", "def f():\n    from train.evaluation.evaluate import load_policy\n", True),
        ("captioner", "import train.environments.tasks\n", True),
        ("envs", "from captioner.grammar import parse\n", True),
        ("envs", "from lcrl.nets import NetConfig\n", True),
        ("lcrl", "def g():\n    import envs.features\n", True),
        ("envs", "from lcrl.errors import LcrlError\n", False),
        ("train", "from captioner.dataset import collect\n", False),
        ("captioner", "from .grammar import parse\n", False),
        ("captioner", "from envs.scene import SceneState\n", False),
    ],
)
def test_the_check_flags_upward_imports_anywhere(package, source, flagged):
    assert bool(violations(source, package, f"{package}/x.py")) == flagged


def test_the_documented_exception_is_lcrl_load_only():
    source = (ROOT / "lcrl" / "__init__.py").read_text()
    upward = [m for _, m in imports_of(source, "lcrl") if m.startswith("train")]
    assert upward and set(upward) == {"train.policies.policy"}


def test_the_benchmarks_are_a_package_that_edits_no_import_path():
    """``benchmarks`` is installed with the other packages, so its scripts import
    ``benchmarks.common`` as they are: none of them edits ``sys.path``."""
    assert (ROOT / "benchmarks" / "__init__.py").is_file()
    scripts = sorted((ROOT / "benchmarks").rglob("*.py"))
    assert len(scripts) > 20  # the walk found the scripts
    bad = [
        f"{path.relative_to(ROOT).as_posix()}:{number}"
        for path in scripts
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if "sys.path" in line
    ]
    assert not bad, "\n".join(bad)


# --- import loops ------------------------------------------------------------------------------
#: The packages of the project, the benchmarks included.
PACKAGES = ("envs", "lcrl", "captioner", "train", "benchmarks")


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph(sources: dict[str, tuple[str, bool]]) -> dict[str, set[str]]:
    """``module -> modules of the project it imports`` from ``{module: (source, is a
    package)}``: every import statement at any depth (a lazy import inside a function
    closes a loop as well as one at the top), those under ``if TYPE_CHECKING:`` aside.
    ``from a import b`` counts as importing ``a.b`` where that is a module."""
    graph: dict[str, set[str]] = {name: set() for name in sources}
    for name, (source, is_package) in sources.items():
        tree = ast.parse(source)
        hints = {
            id(node)
            for block in ast.walk(tree)
            if isinstance(block, ast.If) and "TYPE_CHECKING" in ast.unparse(block.test)
            for node in ast.walk(block)
        }
        here = name if is_package else name.rpartition(".")[0]
        for node in ast.walk(tree):
            if id(node) in hints:
                continue
            found: list[str] = []
            if isinstance(node, ast.Import):
                found = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = here.split(".")[: len(here.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                found = [
                    f"{base}.{alias.name}" if f"{base}.{alias.name}" in sources else base
                    for alias in node.names
                ]
            graph[name] |= {m for m in found if m in sources and m != name}
    return graph


def import_loops(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected sets of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    loops: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for other in sorted(graph[node]):
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            members = []
            while True:
                member = stack.pop()
                members.append(member)
                if member == node:
                    break
            if len(members) > 1:
                loops.append(sorted(members))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return loops


def test_no_package_has_an_import_loop():
    sources = {
        module_name(path): (path.read_text(), path.name == "__init__.py")
        for package in PACKAGES
        for path in sorted((ROOT / package).rglob("*.py"))
    }
    graph = import_graph(sources)
    assert len(graph) > 100 and sum(map(len, graph.values())) > 300  # the walk found them
    loops = import_loops(graph)
    assert not loops, "import loops:\n" + "\n".join(" <-> ".join(loop) for loop in loops)


@pytest.mark.parametrize(
    ("sources", "loops"),
    [
        ({"p.a": ("def f():\n    from p.b import x\n", False), "p.b": ("import p.a\n", False)},
         [["p.a", "p.b"]]),
        ({"p.a": ("from p import b\n", False), "p.b": ("from .a import f\n", False),
          "p": ("", True)}, [["p.a", "p.b"]]),
        ({"p.a": ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from p.b import x\n",
                  False), "p.b": ("import p.a\n", False)}, []),
        ({"p.a": ("import p.b\n", False), "p.b": ("import p.c\n", False),
          "p.c": ("def g():\n    import p.a\n", False)}, [["p.a", "p.b", "p.c"]]),
    ],
)  # fmt: skip
def test_the_loop_check_sees_lazy_and_relative_imports(sources, loops):
    assert import_loops(import_graph(sources)) == loops


# --- room sizes --------------------------------------------------------------------------------
#: The longest a library file may be.
MAX_LINES = 800


def test_no_library_file_is_over_800_lines():
    over, files = [], 0
    for package in ("envs", "lcrl", "captioner", "train"):
        for path in sorted((ROOT / package).rglob("*.py")):
            files += 1
            lines = len(path.read_text().splitlines())
            if lines > MAX_LINES:
                over.append(f"{path.relative_to(ROOT).as_posix()}: {lines} lines")
    assert files > 100  # the walk found the packages
    assert not over, f"split these (at most {MAX_LINES} lines a file):\n" + "\n".join(over)


# --- the rooms of train ------------------------------------------------------------------------
#: The rooms of ``train``, lowest first: a room imports its own modules and those of rooms
#: below it, never one above (lazy imports included).
ROOMS = ("runtime", "environments", "configs", "evaluation", "policies", "training", "commands")


def test_the_rooms_of_train_import_downwards_only():
    rooms = sorted(p.name for p in (ROOT / "train").iterdir() if (p / "__init__.py").is_file())
    assert rooms == sorted(ROOMS)  # every room is placed in the order, and no other is
    loose = sorted(p.name for p in (ROOT / "train").glob("*.py") if p.name != "__init__.py")
    assert not loose, f"modules outside the rooms of train: {loose}"
    rank = {room: i for i, room in enumerate(ROOMS)}
    bad = []
    for room in ROOMS:
        for path in sorted((ROOT / "train" / room).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            for line, module in imports_of(path.read_text(), f"train.{room}"):
                parts = module.split(".")
                if parts[0] == "train" and len(parts) > 1 and rank.get(parts[1], -1) > rank[room]:
                    bad.append(f"{rel}:{line} imports {module} (the room {parts[1]} is above)")
    assert not bad, "\n".join(bad)
