"""Ctrl-C while a posernet command is still starting up.

A command (``posernet-reconstruct``, ``posernet-train``, ...) spends its first second or more
importing torch, OpenCV and SciPy before :func:`posernet.cli.common.run_app` sets up its Ctrl-C
handling. A ``KeyboardInterrupt`` raised inside those imports ends in a long traceback from deep
inside them, or, when it leaves an import half done, in another error (a ``RecursionError``
inside numpy, exit status 1). So when the process is one of posernet's console scripts, this
module, which ``posernet/__init__.py`` imports before anything else, installs a SIGINT handler
that prints the command's one line (``posernet-<cmd>: interrupted``) and ends the process at
once with exit status 130: nothing has been computed or written yet. ``run_app`` replaces it
with the command's own handler as soon as it starts. Imported by any other program (or in a
worker process of a command), it does nothing.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from typing import Any

__all__ = ["install", "interrupted_while_starting"]

EXIT_INTERRUPTED = 130


def _prog() -> str:
    return os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else ""


def interrupted_while_starting(signum: int, frame: Any) -> None:
    """The SIGINT handler while a command imports its modules: one line, exit status 130."""
    try:
        lead = "\n" if sys.stderr.isatty() else ""  # after the terminal's ^C
        sys.stderr.write(f"{lead}{_prog()}: interrupted\n")
        sys.stderr.flush()
    finally:
        os._exit(EXIT_INTERRUPTED)


def install() -> bool:
    """Install :func:`interrupted_while_starting` when this process is a posernet command
    (its script's name starts with ``posernet-``) that still has Python's default SIGINT
    handler, on the main thread of the main process; returns whether it did."""
    if not _prog().startswith("posernet-"):
        return False
    if threading.current_thread() is not threading.main_thread():
        return False
    mp = sys.modules.get("multiprocessing")
    if mp is not None and mp.parent_process() is not None:  # a worker of a command
        return False
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        return False
    signal.signal(signal.SIGINT, interrupted_while_starting)
    return True


install()
