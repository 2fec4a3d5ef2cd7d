"""The one error base of NAC, and how a command line turns errors into exit codes (0 ok, 1 failed, 2 bad input).

Every error meant for the operator derives from NacError and says, in its message, what went wrong and where
(file, line, item, port). CLIs catch only NacError: anything else is a bug and is shown as one.
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


def run_cli(prog: str, command: Callable[[], int]) -> int:
    """Run a CLI command: its exit code, or the error's; a bug prints its traceback and asks to be reported."""
    try:
        return command()
    except NacError as err:
        print(f"{prog}: {err}", file=sys.stderr)
        return err.exit_code
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    except Exception:
        traceback.print_exc()
        print(f"{prog}: internal error (a bug in NAC, not in your input): please report it with the traceback "
              "above and the command you ran", file=sys.stderr)
        return EXIT_FAILED
