"""The MPI build of this node in one line ("MPICH 5.0.2 ch4:ucx ofi"), as peers report it to each other: all
ranks of a job must run the same one (MPICH's ranks talk a wire protocol of their own version and device)."""

from __future__ import annotations

import functools
import re

UNKNOWN_PREFIX = "none: "  # what a node without a usable mpi4py reports


@functools.cache
def mpi_build() -> str:
    """This node's MPI build, or "none: <why>"; loads the MPI library without initialising it."""
    try:
        import mpi4py

        mpi4py.rc.initialize = False  # only asking: MPI_Init would start a singleton job in this process
        mpi4py.rc.finalize = False
        from mpi4py import MPI
    except Exception as err:  # noqa: BLE001 (a broken MPI install raises anything from ImportError to OSError)
        return f"{UNKNOWN_PREFIX}mpi4py cannot load an MPI library ({type(err).__name__}: {err})"
    return summarize(MPI.get_vendor(), MPI.Get_library_version())


def summarize(vendor: tuple[str, tuple], library_version: str) -> str:
    """Name, version and (MPICH) device: what decides whether two ranks can talk."""
    name, version = vendor
    text = f"{name} {'.'.join(str(v) for v in version)}"
    device = re.search(r"^MPICH Device:\s*(.+)$", library_version, re.MULTILINE)
    return f"{text} {device.group(1).strip()}" if device else text
