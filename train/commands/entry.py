"""The ``lcrl`` console script: signals first, then everything else.

Importing the command line (torch, transformers, tyro, the simulators) takes seconds. A
signal in those seconds used to be lost where the shell started ``lcrl`` in the
background (SIGINT ignored: the run then trained on) or to end in a ``KeyboardInterrupt``
traceback in the foreground. This module imports nothing heavy: it makes SIGINT and
SIGTERM stop the process before the command line is imported, so a signal at any instant
ends ``lcrl`` with one line and the shell's status of that signal (130, 143).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
from collections.abc import Sequence
from typing import Any


def _stop(signum: int, frame: Any) -> None:
    """Stop at once: nothing has begun, so there is nothing to save.

    Raising from here is not safe while the command line imports: an exception thrown into
    an extension module's import (pybind11 code calling back into Python) ends the process
    with a C++ ``terminate`` and a core dump instead of the one line and the status.
    """
    print(f"lcrl: interrupted by {signal.Signals(signum).name} while starting", file=sys.stderr)
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a closed pipe: the status says it
            stream.flush()
    os._exit(128 + signum)


def _handled_interrupt() -> None:
    """Clear CPython's mark of an unhandled Ctrl-C.

    A ``KeyboardInterrupt`` that passes through Python code run from C (``PyRun_*``, as
    some extension modules do while they import) marks the interpreter, and at exit it
    then kills itself with SIGINT (status -2, no message) even though the interrupt was
    handled and the status chosen (130). The interrupt is handled here, so the mark goes.
    """
    try:
        import ctypes

        ctypes.c_int.in_dll(ctypes.pythonapi, "_Py_UnhandledKeyboardInterrupt").value = 0
    except (AttributeError, OSError, ValueError):  # another interpreter: nothing to clear
        pass


def main(argv: Sequence[str] | None = None) -> None:
    """Install the stop handlers, import the command line and run it."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _stop)
    try:
        from train.commands.cli import main as cli_main

        cli_main(argv)  # installs the commands' own handlers first thing
    except SystemExit as e:
        if e.code in (128 + signal.SIGINT, 128 + signal.SIGTERM):  # a stop, said and handled
            _handled_interrupt()
        raise


if __name__ == "__main__":
    main()
