"""Following the JSONL logs a running job writes, at a cost that does not grow with the log."""

import json
from pathlib import Path

_followed: dict[tuple[Path, str], tuple[int, int]] = {}  # (log, kind) -> (bytes read, records of kind in them)


def records_logged(path: Path, kind: str) -> int:
    """The records of `kind` in a growing JSONL log so far, read on from where the last call stopped. Re-reading the
    whole log at each poll costs time in proportion to its length: in a clean-clone CI run a test starved in the idle
    class fell ever further behind a fast job, whose log reached 158,000 iterations (467 MiB) in the test's 300 s."""
    offset, count = _followed.get((path, kind), (0, 0))
    try:
        with path.open("rb") as log:
            log.seek(offset)
            chunk = log.read()
    except FileNotFoundError:
        return 0
    whole = chunk.rfind(b"\n") + 1  # a line still being written is read at the next call
    count += sum(json.loads(line)["kind"] == kind for line in chunk[:whole].splitlines())
    _followed[(path, kind)] = (offset + whole, count)
    return count


def first_record(path: Path, kind: str) -> dict:
    """The first record of `kind` in a JSONL log, read no further than it (a job's run_started is its second line)."""
    with path.open("rb") as log:
        for line in log:
            record = json.loads(line)
            if record["kind"] == kind:
                return record
    raise AssertionError(f"no {kind} record in {path}")
