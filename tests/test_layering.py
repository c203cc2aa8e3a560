"""The layers import only downwards: ``envs`` and ``lcrl`` at the bottom, then
``captioner``, then ``train``. Every import statement counts, at module level or inside a
function; the one documented exception is ``lcrl.load`` (and its type hint), which reaches
up into ``train.policy`` when it is called."""

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
ALLOWED = {("lcrl/__init__.py", "train.policy")}


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
        ("captioner", "def f():\n    from train.evaluate import load_policy\n", True),
        ("captioner", "import train.tasks\n", True),
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
    assert upward and set(upward) == {"train.policy"}


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
