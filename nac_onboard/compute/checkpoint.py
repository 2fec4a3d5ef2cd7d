"""The master's checkpoint (results.npz in --out): written atomically by the runner as the job goes, read back by
`--resume` on a restarted master (issue 29), which continues the iteration count and the task's state from it.

It holds `iteration` (the next iteration to run), `task` (the task's name) and the task's arrays (Task.results()).
A checkpoint is a file from a disk that may have been full or a companion that browned out: everything in it is
checked before it is believed, and anything else is refused naming the file and what was expected."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from nac_onboard.errors import BadInput
from nac_onboard.inputs import MAX_AUTOPILOT_LOG_BYTES, check_regular_file
from nac_onboard.records import kinds


def checkpoint_path(out: str | Path) -> Path:
    return Path(out) / kinds.RESULTS.name


def load_checkpoint(out: str | Path, task: str, arrays: bool = True) -> tuple[int, dict[str, np.ndarray]]:
    """(the next iteration, the task's arrays) from the checkpoint in `out`; BadInput naming the file otherwise.
    arrays=False reads only the iteration and the task's name (every rank's check before MPI starts: matmul's
    saved products can be large, and only the master needs them)."""
    path = checkpoint_path(out)
    check_regular_file(path, "--resume checkpoint", MAX_AUTOPILOT_LOG_BYTES)
    try:
        with np.load(path, allow_pickle=False) as data:
            wanted = data.files if arrays else [name for name in data.files if name in ("iteration", "task")]
            read = {name: data[name] for name in wanted}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as err:
        raise BadInput(f"--resume: {path} is not a checkpoint numpy can read ({err})") from None
    iteration, saved_task = read.pop("iteration", None), read.pop("task", None)
    if iteration is None or iteration.shape != () or iteration.dtype.kind not in "iu" or int(iteration) < 0:
        raise BadInput(f"--resume: {path}: expected 'iteration', a whole number >= 0")
    if saved_task is None or saved_task.shape != () or saved_task.dtype.kind != "U":
        raise BadInput(f"--resume: {path}: expected 'task', the name of the task it was written by")
    if str(saved_task) != task:
        raise BadInput(f"--resume: {path} was written by --task {saved_task}, not {task}")
    return int(iteration), read
