"""The ``ballbar`` command's entry point: ``ballbar run|analyze|gcode|report`` (:mod:`.commands`).

Exit codes: 0 success; 1 the input could not be analysed (the one-line message
says what and where); 2 a usage or configuration error.

This module imports next to nothing: ``ballbar run`` installs its SIGTERM and
SIGINT handlers before the subcommands' modules (argparse, logging, TOML, the
analysis, numpy) are loaded, so that a stop at any moment after the
interpreter starts is a clean one (exit 0), and each subcommand then imports
only what it uses.
"""

from __future__ import annotations

import os
import signal
import sys
import threading

TYPE_CHECKING = False  # typing.TYPE_CHECKING without importing typing (mypy reads it the same way)
if TYPE_CHECKING:
    from collections.abc import Sequence
    from types import FrameType


#: BLAS thread pools, one thread each: the fits are small dense problems on a two-core PC beside the machine,
#: where more threads only contend with the sampling thread.  Set by the entry point before numpy loads (the
#: analysis worker, a child, inherits them); the environment wins; importing the library sets nothing.
BLAS_THREADS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    stop = threading.Event()
    asked = subcommand(args)
    if asked == "run":
        _install_stop_handlers(stop)  # first: a SIGTERM from now on is a clean stop, exit 0
    for var in BLAS_THREADS:
        os.environ.setdefault(var, "1")
    from .commands import run_command

    return run_command(args, stop, asked)


def subcommand(args: Sequence[str]) -> str | None:
    """The first argument that is not an option (``ballbar -v run``): the subcommand, if any."""
    return next((a for a in args if not a.startswith("-")), None)


def _install_stop_handlers(stop: threading.Event) -> None:
    def on_signal(signum: int, _frame: FrameType | None) -> None:
        stop.set()
        logging = sys.modules.get("logging")  # no import here: the signal may come in the middle of one
        if logging is not None and hasattr(logging, "getLogger"):
            logging.getLogger(__name__).info("signal %d: stopping", signum)

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)


if __name__ == "__main__":
    sys.exit(main())
