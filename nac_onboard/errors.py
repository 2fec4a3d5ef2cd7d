"""The one error base of NAC, and how a command line turns errors into exit codes (0 ok, 1 failed, 2 bad input).

Every error meant for the operator derives from NacError and says, in its message, what went wrong and where
(file, line, item, port). The one other is the mission library's MissionFileError: `missions` imports the standard
library only, so it cannot derive from NacError; it is bad input (exit 2) all the same. CLIs catch only these two
(`exit_code_of`): anything else is a bug and is shown as one.

SIGTERM (`kill`, `timeout`, systemd's stop) is Ctrl-C in every command run by run_cli: its handler raises
Terminated, a KeyboardInterrupt, in the main thread, so the paths that clean up after Ctrl-C (children stopped,
partial report written) run for it too; the exit code is then 143 (128 + SIGTERM) instead of 130.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
import traceback
from collections.abc import Callable

log = logging.getLogger(__name__)

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_TERMINATED = 0, 1, 2, 130, 128 + signal.SIGTERM
EXIT_BROKEN_PIPE = 128 + signal.SIGPIPE  # what a shell reports for a writer whose reader closed the pipe


class NacError(Exception):
    """An error the operator can act on."""

    exit_code = EXIT_FAILED


class BadInput(NacError, ValueError):
    """A file, argument, message or datagram was not what was expected: exit 2."""

    exit_code = EXIT_BAD_INPUT


class OperationFailed(NacError):
    """The input was fine but the operation could not be done (a vehicle did not answer, a port is taken): exit 1."""

    exit_code = EXIT_FAILED


def exit_code_of(err: BaseException) -> int | None:
    """The exit code of an error meant for the operator (NacError, or the mission library's MissionFileError:
    bad input, 2); None for anything else, a bug."""
    if isinstance(err, NacError):
        return err.exit_code
    from missions.errors import MissionFileError  # only once something failed: most processes read no mission

    return EXIT_BAD_INPUT if isinstance(err, MissionFileError) else None


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread as Ctrl-C is: `except KeyboardInterrupt` handles both."""


def _ignore(signum, frame) -> None:
    pass


def _raise_terminated(signum, frame) -> None:
    # once: a second SIGTERM must not cut the clean-up short (a Python no-op, not SIG_IGN, which children inherit)
    signal.signal(signal.SIGTERM, _ignore)
    raise Terminated(f"signal {signum} (SIGTERM)")


def terminate_as_interrupt():
    """SIGTERM raises Terminated in the main thread (nothing from another thread: signals go to the main one).
    Returns the handler it replaced (None from another thread)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, _raise_terminated)


def interrupted_code(err: KeyboardInterrupt) -> int:
    """130 for Ctrl-C (SIGINT), 143 for SIGTERM."""
    return EXIT_TERMINATED if isinstance(err, Terminated) else EXIT_INTERRUPTED


def run_cli(prog: str, command: Callable[[], int]) -> int:
    """Run a CLI command: its exit code, or the error's; a bug prints its traceback and asks to be reported.
    SIGTERM is handled as Ctrl-C (terminate_as_interrupt): a command that catches KeyboardInterrupt to clean up
    does so for both; a command that installs its own SIGTERM handler (a daemon) replaces this one."""
    previous = terminate_as_interrupt()
    try:
        return command()
    except KeyboardInterrupt as err:
        return interrupted_code(err)
    except BrokenPipeError:  # the reader went away (`| head`): end quietly, as a tool killed by SIGPIPE does
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit's flush
        return EXIT_BROKEN_PIPE
    except Exception as err:
        code = exit_code_of(err)
        if code is not None:
            print(f"{prog}: {err}", file=sys.stderr)
            return code
        traceback.print_exc()
        print(f"{prog}: internal error (a bug in NAC, not in your input): please report it with the traceback "
              "above and the command you ran", file=sys.stderr)
        return EXIT_FAILED
    finally:
        if previous is not None:  # a caller in the same process (a test) gets its own handling back
            signal.signal(signal.SIGTERM, previous)
