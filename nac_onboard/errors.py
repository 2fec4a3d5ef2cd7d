"""The one error base of NAC, and how a command line turns errors into exit codes (0 ok, 1 failed, 2 bad input).

Every error meant for the operator derives from NacError and says, in its message, what went wrong and where
(file, line, item, port). The one other is the mission library's MissionFileError: `missions` imports the standard
library only, so it cannot derive from NacError; it is bad input (exit 2) all the same. CLIs catch only these two
(`exit_code_of`): anything else is a bug and is shown as one.
"""

from __future__ import annotations

import logging
import sys
import traceback
from collections.abc import Callable

log = logging.getLogger(__name__)

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130


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


def run_cli(prog: str, command: Callable[[], int]) -> int:
    """Run a CLI command: its exit code, or the error's; a bug prints its traceback and asks to be reported."""
    try:
        return command()
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    except Exception as err:
        code = exit_code_of(err)
        if code is not None:
            print(f"{prog}: {err}", file=sys.stderr)
            return code
        traceback.print_exc()
        print(f"{prog}: internal error (a bug in NAC, not in your input): please report it with the traceback "
              "above and the command you ran", file=sys.stderr)
        return EXIT_FAILED
