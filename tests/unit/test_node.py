"""The node checks, pure: the doctor's judgement of faked facts, the MPI hostfile from an agent's state, the
MPI-build check naming the odd node out."""

import dataclasses

import pytest

from nac_onboard.errors import BadInput, OperationFailed
from nac_onboard.node import doctor, fleet_mpi
from nac_onboard.node.facts import Facts
from nac_onboard.node.mpi_build import summarize

MPICH = "MPICH 4.3.0 ch4:ofi"
GOOD = Facts(machine="aarch64", os_name="Ubuntu 22.04.4 LTS", glibc="2.35", board="NVIDIA Jetson AGX Orin",
             python="3.10.12", python_path="/opt/nac/venv/bin/python", mpi_build=MPICH,
             mpiexec="/opt/nac/venv/bin/mpiexec", clock_synced=True, clock_note="synchronised (kernel)",
             serial_device="/dev/ttyTHS0", serial_access="ok", disk_path="/var/log/nac", disk_free_bytes=20 * 2**30,
             iperf3="/usr/bin/iperf3", agent_at_boot="enabled")


def needed(facts, role="worker"):
    return [f.text for f in doctor.assess(facts, role) if f.needed]


def test_a_complete_node_needs_nothing_and_each_missing_part_is_named():
    assert doctor.assess(GOOD, "master") == []
    assert "Python 3.6.9 is too old" in needed(dataclasses.replace(GOOD, python="3.6.9"))[0]
    no_mpi = dataclasses.replace(GOOD, mpi_build="none: mpi4py cannot load an MPI library (ImportError: x)")
    assert "no MPI" in needed(no_mpi)[0]
    assert needed(dataclasses.replace(GOOD, mpiexec=None), "worker") == []
    assert "no mpiexec" in needed(dataclasses.replace(GOOD, mpiexec=None), "master")[0]
    port = dataclasses.replace(GOOD, serial_access="/dev/ttyTHS0: this user may not read and write it (...)")
    assert "/dev/ttyTHS0" in needed(port)[0]
    assert "MB free" in needed(dataclasses.replace(GOOD, disk_free_bytes=100 * 2**20))[0]
    unsynced = doctor.assess(dataclasses.replace(GOOD, clock_synced=False, clock_note="not synchronised"), "worker")
    assert [f.needed for f in unsynced] == [False] and "chrony" in unsynced[0].text, "advice, not a failure"
    not_at_boot = doctor.assess(dataclasses.replace(GOOD, agent_at_boot="disabled"), "worker")
    assert [f.needed for f in not_at_boot] == [False] and "rebooted worker rejoins" in not_at_boot[0].text
    text = doctor.report(GOOD, "worker", [])
    assert "glibc 2.35" in text and MPICH in text and "has what a worker needs" in text


def test_the_mpi_build_line_keeps_what_decides_whether_ranks_can_talk():
    library = "MPICH Version:      4.3.0\nMPICH Release date: x\nMPICH Device:       ch4:ofi\nMPICH CC: cc\n"
    assert summarize(("MPICH", (4, 3, 0)), library) == MPICH
    assert summarize(("Open MPI", (4, 1, 2)), "Open MPI v4.1.2, package: Debian") == "Open MPI 4.1.2"


def state(*peers, me_role="master", me_build=MPICH):
    return {"self": {"id": "master", "role": me_role, "mpi_build": me_build},
            "peers": {p["id"]: {"role": "worker", "lost": False, "age_s": 0.2, "mpi_build": MPICH, **p}
                      for p in peers}}


def test_the_hostfile_lists_the_master_then_the_live_workers_by_id():
    nodes, notes = fleet_mpi.job_nodes(state({"id": "w2", "host": "10.0.0.12"}, {"id": "w1", "host": "10.0.0.11"},
                                             {"id": "w3", "host": "10.0.0.13", "lost": True}), "10.0.0.10")
    text = fleet_mpi.hostfile_text(nodes)
    assert [line for line in text.splitlines() if not line.startswith("#")] == \
        ["10.0.0.10:1", "10.0.0.11:1", "10.0.0.12:1"]
    assert "# rank 1: w1 (worker, MPICH 4.3.0 ch4:ofi)" in text
    assert notes == ["w3: lost (last heard 0.2 s ago), left out"]
    assert fleet_mpi.check_builds(nodes) == MPICH
    with pytest.raises(BadInput, match="run this on the master"):
        fleet_mpi.job_nodes(state({"id": "w1", "host": "10.0.0.11"}, me_role="worker"), "10.0.0.10")
    with pytest.raises(OperationFailed, match="no live worker"):
        fleet_mpi.job_nodes(state({"id": "w1", "host": "10.0.0.11", "lost": True}), "10.0.0.10")


def test_the_build_check_names_the_node_that_differs_or_reports_none():
    nodes, _ = fleet_mpi.job_nodes(state({"id": "w1", "host": "10.0.0.11"},
                                         {"id": "w2", "host": "10.0.0.12", "mpi_build": "Open MPI 4.1.2"}),
                                   "10.0.0.10")
    with pytest.raises(fleet_mpi.MpiBuildMismatch, match=r"w2 \(10.0.0.12\) runs 'Open MPI 4.1.2'") as err:
        fleet_mpi.check_builds(nodes)
    assert "2 of 3 nodes run 'MPICH 4.3.0 ch4:ofi'" in str(err.value) and "w1" not in str(err.value)
    assert err.value.exit_code == 2
    nodes, _ = fleet_mpi.job_nodes(state({"id": "w1", "host": "10.0.0.11", "mpi_build": ""}), "10.0.0.10")
    with pytest.raises(fleet_mpi.MpiBuildMismatch, match="w1 .* reports no MPI build"):
        fleet_mpi.check_builds(nodes)
    # a tie: the master's build is the reference, so the worker is the odd one out
    nodes, _ = fleet_mpi.job_nodes(state({"id": "w1", "host": "10.0.0.11", "mpi_build": "MPICH 3.3 ch3:nemesis"}),
                                   "10.0.0.10")
    with pytest.raises(fleet_mpi.MpiBuildMismatch, match="w1 .* runs 'MPICH 3.3 ch3:nemesis'"):
        fleet_mpi.check_builds(nodes)
