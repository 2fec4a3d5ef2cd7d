"""CLIs turn the one error base into exit codes, and show a bug as a bug."""

from missions.errors import MissionFileError
from nac_onboard.errors import EXIT_BAD_INPUT, BadInput, OperationFailed, exit_code_of, run_cli


def _raise(error):
    def command():
        raise error
    return command


def test_operator_errors_become_their_exit_codes(capsys):
    assert run_cli("nac-x", _raise(BadInput("plan.plan: item 3: latitude 91 outside -90..90"))) == 2
    assert run_cli("nac-x", _raise(OperationFailed("vehicle 1 did not answer"))) == 1
    assert run_cli("nac-x", lambda: 0) == 0
    err = capsys.readouterr().err
    assert "nac-x: plan.plan: item 3" in err and "Traceback" not in err


def test_the_mission_librarys_own_error_is_bad_input(capsys):
    """missions imports the standard library only, so its error is not a NacError: the CLIs still exit 2 with it."""
    err = MissionFileError("x.plan", "item 4 (doJumpId 4)", "latitude 95.0 is outside -90..90")
    assert exit_code_of(err) == MissionFileError.exit_code == EXIT_BAD_INPUT and isinstance(err, ValueError)
    assert run_cli("nac-x", _raise(err)) == 2
    assert capsys.readouterr().err == "nac-x: x.plan: item 4 (doJumpId 4): latitude 95.0 is outside -90..90\n"
    assert exit_code_of(RuntimeError("bug")) is None


def test_a_programming_error_is_a_traceback_asking_to_be_reported(capsys):
    assert run_cli("nac-x", _raise(KeyError("boom"))) == 1
    err = capsys.readouterr().err
    assert "Traceback" in err and "KeyError" in err and "please report it" in err


def test_a_runtime_error_is_not_mistaken_for_an_operator_error(capsys):
    assert run_cli("nac-x", _raise(RuntimeError("internal"))) == 1
    assert "please report it" in capsys.readouterr().err


def test_interrupt_is_130():
    assert run_cli("nac-x", _raise(KeyboardInterrupt())) == 130


def test_sigterm_is_ctrl_c_with_exit_143_and_the_callers_handler_comes_back():
    """SIGTERM raises KeyboardInterrupt (Terminated) in the command, so its Ctrl-C clean-up runs; exit 143."""
    import signal

    from nac_onboard.errors import Terminated

    cleaned = []

    def command():
        try:
            signal.raise_signal(signal.SIGTERM)  # its handler runs before raise_signal returns
            return 0
        except KeyboardInterrupt as err:
            cleaned.append(type(err))
            raise

    before = signal.getsignal(signal.SIGTERM)
    assert run_cli("nac-x", command) == 143
    assert cleaned == [Terminated]
    assert signal.getsignal(signal.SIGTERM) is before


def test_a_reader_that_closes_the_pipe_ends_the_command_quietly():
    """`nac-sitl radio ... | head -1`: the table stops where head stopped reading, with the exit status a shell
    gives a writer killed by SIGPIPE (141) and no traceback. 3,000 distances make some 150 KB of table, more than
    a pipe holds (64 KB), so the writer meets the closed pipe however fast head exits."""
    import subprocess
    import sys
    from pathlib import Path

    cli = Path(sys.executable).parent / "nac-sitl"
    distances = ",".join(f"{1 + k * 0.01:.2f}" for k in range(3000))
    done = subprocess.run(["bash", "-c", f"set -o pipefail; {cli} radio wifi-flight --draws 10 --distances-m "
                                         f"{distances} | head -1; echo \"status ${{PIPESTATUS[0]}}\""],
                          capture_output=True, text=True, timeout=60)
    assert done.stdout.splitlines()[-1] == "status 141" and done.stderr == "", (done.stdout[-300:], done.stderr)
