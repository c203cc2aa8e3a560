"""The README and docs/ are tested: every command they show runs, every link resolves.

Which commands: every line of a fenced ``bash`` / ``sh`` / ``shell`` block (``\\``
continuations joined; blank lines and ``#`` comments skipped: output is shown as ``#``
comments there), and every ``$ ``-prefixed line of a ``console`` block (the lines after it
are output; a documented ``lcrl: error: ...`` line must be exactly the error the command
prints, with exit status 2). ``python`` blocks run too, except fragments (a line starting
with ``...``) and the pages of :data:`PYTHON_EXCERPTS`.

How each command runs, in the order of its page, in a fresh folder per page (so a page's
commands build on each other as they would for a reader):

* ``lcrl ...`` runs in-process (``train.commands.cli.main``) with tiny-size options appended
  (later options win): ``lcrl train`` gets :data:`TINY_TRAIN`, ``lcrl eval`` 2 episodes,
  ``lcrl act`` 1 episode, ``lcrl demos record`` 4 episodes, ``lcrl caption`` 2 gradient
  steps of small networks, a canonical reader 2 members of 40 steps, and so on
  (:func:`shrink`). Nothing gets ``--overwrite``: a page that writes twice to one place
  fails, as it would for a reader. Inputs a page uses but does not make itself
  (``runs/main``, a demonstration file, ``mine.txt``, a robomimic file) are made first
  (:meth:`Workspace.provide`): a tiny ``lang2d-quick`` run for most run names, a tiny
  ``lang2d-tasks`` / ``lang2d-bc`` / ``state2d`` run for names with ``tasks`` / ``bc`` /
  ``state``. ``printf TEXT | lcrl ...`` feeds TEXT to the standard input. ``--agent.device
  cuda`` becomes ``cpu`` on a machine without CUDA.
* ``python examples/X.py ARGS`` runs the example.
* ``python benchmarks/X.py ARGS`` and ``python -m MODULE ARGS`` take hours, so only their
  arguments are checked: the script runs up to its ``ArgumentParser.parse_args`` and stops
  there (a script without an argument parser must be shown without arguments).
* ``make TARGET [VAR=value]``: the Makefile must have the target (and the variable).

Commands that need robosuite or gymnasium-robotics (:func:`is_slow`) run in the ``slow``
test only. :data:`SKIP` lists the commands that are not run at all (none today). Anything
else fails the test, so a new kind of command needs a handler here or a documented skip.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import itertools
import json
import os
import re
import runpy
import shlex
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from helpers import cli

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
#: Pages whose commands run, and pages whose links are checked.
PAGES = [README, *DOCS, ROOT / "benchmarks" / "results" / "README.md"]
SHELL_LANGS = {"bash", "sh", "shell", "console"}
MAX_README_LINES = 250

#: Commands that are not run (a prefix of the command line -> why). Keep it short.
SKIP: dict[str, str] = {}
#: Pages whose python blocks are not run, because they are excerpts of files that run them
#: (page -> those files); their shell commands still run, and
#: :func:`test_python_excerpts_match_their_files` checks each block against the files.
PYTHON_EXCERPTS: dict[str, tuple[str, ...]] = {
    # tests/test_extending.py runs the simulator, the goal modality and the registrations;
    # the algorithm's spec is the one lcrl/algos/sac.py ends with
    "docs/extending.md": ("tests/test_extending.py", "lcrl/algos/sac.py"),
}

#: Appended to every ``lcrl train`` command (a later option wins).
TINY_TRAIN = [
    "--total-steps", "60", "--learning-starts", "20", "--batch-size", "16",
    "--eval-episodes", "2", "--eval-every", "0", "--checkpoint-every", "0",
    "--log-every", "20", "--no-progress", "--no-tensorboard", "--buffer.capacity", "2000",
    "--agent.net.hidden", "16", "16", "--agent.net.text-dim", "8",
]  # fmt: skip
TINY_CAPTION_TRAIN = [
    "--steps", "2", "--batch-size", "4", "--model.features", "16", "--model.hidden", "16",
    "--model.embed", "8", "--model.text-features", "8", "--no-progress",
]  # fmt: skip
TINY_PERCEPTION_TRAIN = [
    "--steps", "10", "--batch-size", "8", "--model.channels", "8", "8",
    "--model.strides", "2", "2", "--model.hidden", "16", "--no-progress",
]  # fmt: skip
#: The lcrl subcommands that run on the 2D tabletop: each must appear in a page's
#: default (not slow) commands.
FAMILIES_2D = {
    "train", "eval", "act", "report", "demo", "split", "parse", "caption collect",
    "caption train", "caption eval", "demos record", "demos relabel", "demos info",
    "demos import-robomimic", "perception collect", "perception train", "perception eval",
    "distill", "route", "ensemble", "export",
}  # fmt: skip
INSTRUCTIONS_FILE = """\
# mine.txt
touch the red block
move to the green cylinder please
wave at the camera          # runs, not checked
"""


# --------------------------------------------------------------------------- extraction
@dataclass
class Step:
    """One command, or one python block, of a page."""

    page: str
    line: int
    argv: list[str] = field(default_factory=list)
    stdin: str | None = None
    error: str | None = None  # the documented ``lcrl: error: ...`` line
    code: str | None = None  # a python block

    def __str__(self) -> str:
        what = "python block" if self.code is not None else shlex.join(self.argv)
        return f"{self.page}:{self.line}: {what}"


def fenced_blocks(text: str) -> list[tuple[str, int, list[str]]]:
    """``(language, line of the first content line, lines)`` of every fenced block
    (indented fences inside list items included)."""
    blocks, lang, start, body = [], None, 0, []
    for i, raw in enumerate(text.splitlines(), 1):
        stripped = raw.strip()
        if lang is None:
            if stripped.startswith("```"):
                lang, start, body = stripped[3:].strip().lower(), i + 1, []
                indent = len(raw) - len(raw.lstrip())
        elif stripped == "```":
            blocks.append((lang, start, body))
            lang = None
        else:
            body.append(raw[indent:] if raw[:indent].strip() == "" else raw)
    return blocks


def _joined(lines: list[str], start: int) -> list[tuple[int, str]]:
    """Lines with their ``\\`` continuations joined: ``(line number, text)``."""
    out: list[tuple[int, str]] = []
    pending: tuple[int, str] | None = None
    for k, line in enumerate(lines):
        if pending is not None:
            text = pending[1] + " " + line.strip()
            number = pending[0]
        else:
            text, number = line, start + k
        if text.rstrip().endswith("\\"):
            pending = (number, text.rstrip()[:-1])
        else:
            pending = None
            out.append((number, text))
    return out


def _step(page: str, number: int, text: str) -> Step:
    tokens = shlex.split(text, comments=True)
    if "|" in tokens:  # printf TEXT | command
        cut = tokens.index("|")
        feed, tokens = tokens[:cut], tokens[cut + 1 :]
        assert feed[0] == "printf" and len(feed) == 2, f"{page}:{number}: unsupported pipe"
        stdin = feed[1].encode().decode("unicode_escape")
        return Step(page, number, tokens, stdin=stdin)
    return Step(page, number, tokens)


def steps_of(text: str, page: str) -> list[Step]:
    """The commands and python blocks of a page's text, in order."""
    steps: list[Step] = []
    for lang, start, lines in fenced_blocks(text):
        if lang == "python":
            if not any(line.lstrip().startswith("...") for line in lines):
                steps.append(Step(page, start, code="\n".join(lines) + "\n"))
        elif lang == "console":
            joined = _joined(lines, start)
            for k, (number, text) in enumerate(joined):
                if text.startswith("$ "):
                    step = _step(page, number, text[2:])
                    after = joined[k + 1][1] if k + 1 < len(joined) else ""
                    if after.startswith("lcrl: error:"):
                        step.error = after.strip()
                    steps.append(step)
        elif lang in SHELL_LANGS:
            for number, text in _joined(lines, start):
                if text.strip() and not text.lstrip().startswith("#"):
                    steps.append(_step(page, number, text))
    return steps


def page_steps(path: Path) -> list[Step]:
    return steps_of(path.read_text(), path.relative_to(ROOT).as_posix())


def is_slow(argv: list[str]) -> bool:
    """Commands that need robosuite or gymnasium-robotics (and minutes)."""
    if argv[:1] != ["lcrl"]:
        return False
    train_preset = argv[2] if argv[1:2] == ["train"] and len(argv) > 2 else ""
    values = {a for k, a in itertools.pairwise(argv) if k in ("--preset", "--env")}
    names = {train_preset, *values}
    data = {a for k, a in itertools.pairwise(argv) if k == "--data"}  # robosuite frames
    if argv[1:2] == ["distill"] and len(argv) > 2:  # the teacher's run names its simulator
        data.add(argv[2])
    return any(n.startswith("robosuite") or n == "fetch-reach" for n in names) or any(
        "robosuite" in d for d in data
    )


def family(argv: list[str]) -> str:
    """The lcrl subcommand of a command line (``caption train``, ``demos record``, ...)."""
    if (
        argv[1] in ("caption", "demos", "perception")
        and len(argv) > 2
        and not argv[2].startswith("-")
    ):
        return f"{argv[1]} {argv[2]}"
    return argv[1]


def _option(argv: list[str], name: str) -> str | None:
    """The value of the last ``name VALUE`` in argv."""
    values = [b for a, b in itertools.pairwise(argv) if a == name]
    return values[-1] if values else None


def _positionals(argv: list[str], skip: int) -> list[str]:
    """Positional arguments after the first ``skip`` tokens, up to the first option."""
    out = []
    for token in argv[skip:]:
        if token.startswith("-"):
            break
        out.append(token)
    return out


def shrink(argv: list[str]) -> list[str]:
    """The command at a tiny size (options appended: the last occurrence wins)."""
    argv = list(argv)
    if "--help" in argv or "-h" in argv:
        return argv
    if not torch.cuda.is_available():
        argv = argv[:1] + [
            "cpu" if before == "--agent.device" and a.startswith("cuda") else a
            for before, a in itertools.pairwise(argv)
        ]
    sub = family(argv)
    if sub == "demos record" and "random" in argv:  # random play: enough to relabel
        return [*argv, "--episodes", "40", "--no-progress"]
    if sub == "train":
        extra = list(TINY_TRAIN)
        if "--resume" in argv:  # continue past the tiny run it resumes
            extra[1] = str(2 * int(TINY_TRAIN[1]))
        return argv + extra
    return argv + {
        "eval": ["--episodes", "2", "--no-progress"],
        "act": ["--episodes", "1"],
        "demo": ["--episodes", "2", "--max-steps", "10", "--image-size", "48"],
        "caption collect": ["--episodes", "4", "--max-episode-steps", "10", "--no-progress"],
        "caption merge": ["--no-progress"],
        "caption train": TINY_CAPTION_TRAIN,
        "caption eval": ["--max-pairs", "20"],
        "demos record": ["--episodes", "4", "--no-progress"],
        "demos relabel": ["--no-progress"],
        "demos import-robomimic": ["--no-progress"],
        "perception collect": ["--episodes", "8", "--max-episode-steps", "10", "--no-progress"],
        "perception train": TINY_PERCEPTION_TRAIN,
        "distill": ["--rounds", "1", "--episodes-per-round", "2", "--updates-per-round", "4",
                    "--batch-size", "8", "--eval-episodes", "1", "--no-progress",
                    "--no-tensorboard"],
    }.get(sub, [])  # fmt: skip


# --------------------------------------------------------------------------- running
@contextlib.contextmanager
def working_directory(path: Path):
    """``contextlib.chdir`` (Python 3.11+) for Python 3.10."""
    before = Path.cwd()
    os.chdir(path)
    try:
        yield
    finally:
        os.chdir(before)


def run_lcrl(argv: list[str], stdin: str | None = None) -> tuple[int, str, str]:
    """``lcrl ARGV[1:]`` in-process: (exit status, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    old_stdin = sys.stdin
    sys.stdin = io.StringIO(stdin or "")
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = cli(*argv[1:])
    finally:
        sys.stdin = old_stdin
    return code, out.getvalue(), err.getvalue()


def _check(argv: list[str], stdin: str | None = None) -> str:
    code, out, err = run_lcrl(argv, stdin)
    assert code == 0, f"{shlex.join(argv)} exited with {code}:\n{err[-3000:]}"
    return out


def write_robomimic(path: Path) -> None:
    """A small LIBERO-style robomimic file: 2 demos with a language instruction."""
    rng = np.random.default_rng(0)
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["env_args"] = json.dumps({"env_name": "Libero", "type": 1})
        data.attrs["problem_info"] = json.dumps({"language_instruction": "open the drawer"})
        for i, t in enumerate((6, 8)):
            g = data.create_group(f"demo_{i}")
            g.create_dataset("obs/robot0_eef_pos", data=rng.normal(size=(t, 3)))
            g.create_dataset("obs/object", data=rng.normal(size=(t, 4)))
            g.create_dataset("obs/robot0_gripper_qpos", data=rng.normal(size=(t, 2)))
            g.create_dataset(
                "obs/agentview_image", data=rng.integers(0, 256, (t, 8, 8, 3), dtype=np.uint8)
            )
            g.create_dataset("actions", data=rng.uniform(-1.2, 1.2, (t, 7)))
            g.create_dataset("rewards", data=np.zeros(t))


class Cache:
    """Tiny runs and files made once per test session, copied into pages' folders."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.made: dict[str, Path] = {}

    def _in(self, name: str, make) -> Path:
        if name not in self.made:
            with working_directory(self.folder):
                make()
            self.made[name] = self.folder / name
        return self.made[name]

    def demos(self) -> Path:
        def make():
            _check(shrink(["lcrl", "demos", "record", "--preset", "lang2d", "--out", "d.h5"]))
            _check(shrink(["lcrl", "demos", "relabel", "d.h5", "--out", "demos.h5"]))

        return self._in("demos.h5", make)

    def run(self, kind: str) -> Path:
        preset = {"tasks-lang": "lang2d-tasks-lang", "tasks": "lang2d-tasks", "bc": "lang2d-bc",
                  "state": "state2d"}.get(kind, "lang2d-quick")  # fmt: skip
        extra = ["--demos", str(self.demos())] if preset == "lang2d-bc" else []
        name = f"runs/{preset}"
        return self._in(
            name, lambda: _check(shrink(["lcrl", "train", preset, "--out", name, *extra]))
        )


def run_kind(name: str) -> str:
    base = Path(name).name
    for kind in ("tasks-lang", "tasks", "bc", "state"):
        if kind in base:
            return kind
    return "quick"


class Workspace:
    """A page's folder: commands run there, inputs it lacks are copied in from the cache."""

    def __init__(self, folder: Path, cache: Cache) -> None:
        self.folder = folder
        self.cache = cache

    def provide(self, step: Step) -> None:
        runs: list[str] = []
        demos: list[str] = []
        argv = step.argv
        if step.code is not None:
            runs = re.findall(r"[\"'](runs/[\w.-]+)", step.code)
            demos = re.findall(r"[\"'](data/[\w.-]+\.h5)", step.code)
        elif argv[:1] == ["lcrl"] and "--help" not in argv:
            sub = family(argv)
            if sub in ("eval", "act"):
                runs = _positionals(argv, 2)[:1]
            elif sub == "report":
                runs = _positionals(argv, 2)
            elif sub == "caption eval":
                runs = _positionals(argv, 3)[:1]
            elif sub in ("demos relabel", "demos info"):
                demos = _positionals(argv, 3)[:1]
            elif sub == "demos import-robomimic":
                for src in _positionals(argv, 3)[:1]:
                    if not (self.folder / src).exists():
                        write_robomimic(self.folder / src)
            elif sub == "train" and "--resume" in argv:  # a run the page did not train
                self.train(argv[2], _option(argv, "--out"))
            elif sub == "distill":  # a robosuite teacher the page did not train
                for name in _positionals(argv, 2)[:1]:
                    if "robosuite" in name:
                        self.train("robosuite-manip", name)
            runs += [v for v in [_option(argv, "--policy")] if v]
            demos += [v for v in [_option(argv, "--demos")] if v]
            instructions = _option(argv, "--instructions")
            if instructions and not (self.folder / instructions).exists():
                (self.folder / instructions).write_text(INSTRUCTIONS_FILE)
        elif argv[:1] == ["python"] and argv[1].startswith("examples/"):
            runs = [a for a in argv[2:] if a.startswith("runs/")]
        for name in runs:
            if not (self.folder / name).exists():
                shutil.copytree(self.cache.run(run_kind(name)), self.folder / name)
        for name in demos:
            if not (self.folder / name).exists():
                (self.folder / name).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy(self.cache.demos(), self.folder / name)

    def train(self, preset: str, out: str | None) -> None:
        """A tiny run of ``preset`` at ``out``, unless the page has one there."""
        if out and not (self.folder / out).exists():
            with working_directory(self.folder):
                _check(shrink(["lcrl", "train", preset, "--out", out]))

    def run(self, step: Step) -> None:
        self.provide(step)
        with working_directory(self.folder):
            if step.code is not None:
                run_python_block(step)
            elif step.argv[0] == "lcrl":
                run_lcrl_step(step)
            elif step.argv[0] == "make":
                check_make(step)
            elif step.argv[:1] == ["python"] and step.argv[1].startswith("examples/"):
                run_example(step)
            elif step.argv[:1] == ["python"]:
                check_script_arguments(step)
            else:
                pytest.fail(f"{step}: no handler for this command (add one, or a SKIP entry)")


def run_lcrl_step(step: Step) -> None:
    code, _, err = run_lcrl(shrink(step.argv), step.stdin)
    if step.error is not None:
        lines = err.strip().splitlines()
        assert code == 2, f"{step}: expected the documented error, got status {code}"
        assert lines and lines[-1] == step.error, f"{step}: documented error differs:\n{err}"
    else:
        assert code == 0, f"{step}: exited with {code}:\n{err[-3000:]}"


def run_python_block(step: Step) -> None:
    old_argv = sys.argv
    sys.argv = [step.page]
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            exec(compile(step.code, str(step), "exec"), {"__name__": "__docs__"})
    finally:
        sys.argv = old_argv


def run_example(step: Step) -> None:
    old_argv = sys.argv
    sys.argv = [step.argv[1], *step.argv[2:]]
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            runpy.run_path(str(ROOT / step.argv[1]), run_name="__main__")
    finally:
        sys.argv = old_argv


class _ArgumentsParsed(Exception):
    pass


def check_script_arguments(step: Step) -> None:
    """A benchmark script or module: its argument parser accepts the documented arguments
    (the script stops right after parsing them)."""
    if step.argv[1] == "-m":
        module, args = step.argv[2], step.argv[3:]
        path = ROOT / (module.replace(".", "/") + ".py")
    else:
        path, args = ROOT / step.argv[1], step.argv[2:]
    assert path.is_file(), f"{step}: no {path.relative_to(ROOT)}"
    source = path.read_text()
    if "ArgumentParser(" not in source or ".parse_args(" not in source:
        assert not args, f"{step}: {path.name} takes no arguments"
        return
    original = argparse.ArgumentParser.parse_args

    def parse_then_stop(self, args=None, namespace=None):
        original(self, args, namespace)
        raise _ArgumentsParsed

    old_argv = sys.argv
    sys.argv = [str(path), *args]
    argparse.ArgumentParser.parse_args = parse_then_stop
    try:
        with (
            pytest.raises(_ArgumentsParsed),
            contextlib.redirect_stdout(io.StringIO()),
            contextlib.redirect_stderr(io.StringIO()) as err,
        ):
            try:
                if step.argv[1] == "-m":
                    runpy.run_module(module, run_name="__main__", alter_sys=True)
                else:
                    runpy.run_path(str(path), run_name="__main__")
            except SystemExit as e:
                pytest.fail(f"{step}: the arguments are refused: {err.getvalue()} ({e.code})")
    finally:
        argparse.ArgumentParser.parse_args = original
        sys.argv = old_argv


def check_make(step: Step) -> None:
    makefile = (ROOT / "Makefile").read_text()
    targets = set(re.findall(r"^([\w.-]+)\s*:(?!=)", makefile, re.M))
    for arg in step.argv[1:]:
        if "=" in arg:
            var = arg.split("=")[0]
            assert re.search(rf"^{var}\s*[?:]?=", makefile, re.M), f"{step}: no {var} variable"
        else:
            assert arg in targets, f"{step}: the Makefile has no {arg!r} target"


def skipped(step: Step) -> bool:
    if step.code is not None:
        return step.page in PYTHON_EXCERPTS
    return any(shlex.join(step.argv).startswith(p) for p in SKIP)


# --------------------------------------------------------------------------- tests
@pytest.fixture(scope="module")
def cache(tmp_path_factory, one_thread):
    return Cache(tmp_path_factory.mktemp("docs-cache"))


def _run_page(page: Path, slow: bool, tmp_path: Path, cache: Cache) -> None:
    """Run a page's default (or slow) steps in order in ``tmp_path``."""
    ws = Workspace(tmp_path, cache)
    for step in page_steps(page):
        if skipped(step):
            continue
        if (step.code is not None and slow) or (step.code is None and is_slow(step.argv) != slow):
            continue
        start = time.perf_counter()
        ws.run(step)
        print(f"ran {step} ({time.perf_counter() - start:.1f} s)")  # shown with pytest -s


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_page_commands_run(page, tmp_path, cache, tiny_canonical_reader):
    # a canonical reader a tiny run needs is fitted at tiny size too; the slow pages' kept
    # models load theirs as kept
    _run_page(page, False, tmp_path, cache)


@pytest.mark.slow
@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_page_commands_run_slow(page, tmp_path, cache):
    _run_page(page, True, tmp_path, cache)


def test_every_2d_command_family_is_run_by_default():
    shown = {
        family(s.argv)
        for page in PAGES
        for s in page_steps(page)
        if s.argv[:1] == ["lcrl"] and not is_slow(s.argv) and "--help" not in s.argv
    }
    assert shown >= FAMILIES_2D, f"not shown in a default command: {FAMILIES_2D - shown}"


def test_extraction_conventions():
    text = """
```bash
lcrl eval runs/x \\
    --episodes 5   # a comment
# lcrl not a command
printf 'a\\nb\\n' | lcrl act runs/x --interactive
```

```console
$ lcrl train lang2d --buffer.k 4
lcrl: error: something
$ lcrl parse "push it"
output
```

```python
x = 1
```

```python
...
```
"""
    blocks = fenced_blocks(text)
    assert [b[0] for b in blocks] == ["bash", "console", "python", "python"]
    steps = steps_of(text, "check.md")
    assert len(steps) == 5  # the fragment (a ``...`` line) is not run
    assert steps[4].code == "x = 1\n"
    assert steps[0].argv == ["lcrl", "eval", "runs/x", "--episodes", "5"]
    assert steps[1].stdin == "a\nb\n" and steps[1].argv[:2] == ["lcrl", "act"]
    assert steps[2].error == "lcrl: error: something"
    assert steps[3].argv == ["lcrl", "parse", "push it"] and steps[3].error is None
    assert shrink(["lcrl", "eval", "runs/x"])[-3:] == ["--episodes", "2", "--no-progress"]
    assert is_slow(["lcrl", "train", "robosuite-image"]) and is_slow(
        ["lcrl", "train", "fetch-reach"]
    )
    assert is_slow(["lcrl", "demos", "record", "--preset", "robosuite"])
    assert not is_slow(["lcrl", "train", "lang2d"])


def test_readme_is_short():
    lines = README.read_text().splitlines()
    assert len(lines) <= MAX_README_LINES, f"README.md has {len(lines)} lines"


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower().replace("`", ""))
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    out = set()
    in_block = False
    for line in path.read_text().splitlines():
        if line.strip().startswith("```"):
            in_block = not in_block
        elif not in_block and line.startswith("#"):
            out.add(_slug(line.lstrip("#")))
    return out


def test_relative_links_resolve():
    bad = []
    for page in PAGES:
        text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
        text = re.sub(r"`[^`\n]*`", "", text)
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if re.match(r"[a-z]+:", target):
                continue  # http:, https:, mailto:
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            if not dest.exists():
                bad.append(f"{page.relative_to(ROOT)}: {target} (no such file)")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                bad.append(f"{page.relative_to(ROOT)}: {target} (no such heading)")
    assert not bad, "\n".join(bad)


def test_docs_index_and_readme_link_every_page():
    index = (ROOT / "docs" / "README.md").read_text()
    readme = README.read_text()
    for page in DOCS:
        if page.name != "README.md":
            assert f"]({page.name}" in index, f"docs/README.md does not link {page.name}"
            assert f"](docs/{page.name}" in readme, f"README.md does not link {page.name}"
    assert "](benchmarks/results/README.md" in readme


def code_lines(text: str) -> list[str]:
    """The code of a Python text line by line: comments dropped (``#`` after a space or
    at the start), whitespace runs made one space, blank lines skipped."""
    lines = []
    for line in text.splitlines():
        code = " ".join(re.sub(r"(^|\s)#.*$", "", line).split())
        if code:
            lines.append(code)
    return lines


def excerpt_of(block: str, source: str) -> str | None:
    """None when every code line of ``block`` appears in ``source``, in order (an excerpt
    may leave lines out); else the first line that does not."""
    have = code_lines(source)
    at = 0
    for line in code_lines(block):
        try:
            at = have.index(line, at) + 1
        except ValueError:
            return line
    return None


@pytest.mark.parametrize("page", sorted(PYTHON_EXCERPTS))
def test_python_excerpts_match_their_files(page):
    """Every python block of an excerpt page is an excerpt of one of its files: its code
    lines appear there in the same order (comments and spacing aside), so the snippets
    cannot drift from the code that the tests run."""
    sources = {name: (ROOT / name).read_text() for name in PYTHON_EXCERPTS[page]}
    text = (ROOT / page).read_text()
    blocks = [(n, "\n".join(b)) for lang, n, b in fenced_blocks(text) if lang == "python"]
    assert blocks, f"{page} has no python block"
    for number, code in blocks:
        missing = {name: excerpt_of(code, text) for name, text in sources.items()}
        if None not in missing.values():
            lines = "; ".join(f"{name}: {line!r}" for name, line in missing.items())
            pytest.fail(f"{page}:{number}: the block is in none of its files ({lines})")


def test_excerpt_check_sees_a_changed_line():
    source = "def f(x):\n    return x + 1  # one more\n"
    assert excerpt_of("def f(x):\n    return x + 1", source) is None
    assert excerpt_of("def   f(x):  # a comment\n\n  return x + 1\n", source) is None
    assert excerpt_of("def f(x):\n    return x + 2", source) == "return x + 2"
    assert excerpt_of("return x + 1\ndef f(x):", source) == "def f(x):"  # order counts


def test_querying_example_is_the_tested_script():
    """The Python example of docs/querying.md is examples/query_policy.py (which
    test_act_api runs on a tiny checkpoint)."""
    blocks = [b for b in fenced_blocks((ROOT / "docs" / "querying.md").read_text())]
    code = next("\n".join(lines) for lang, _, lines in blocks if lang == "python")
    assert code in (ROOT / "examples" / "query_policy.py").read_text()
