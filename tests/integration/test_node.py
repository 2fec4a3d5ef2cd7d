"""The node commands against real agents and a real mpiexec: the hostfile from the peers the master's agent
hears, the MPI-build check before a job (a fake node that disagrees: exit 2 naming it, nothing started), and the
doctor naming a missing serial port."""

import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from nac_onboard.agent.state_feed import fetch_state
from nac_onboard.compute import forestfires, kernels
from nac_onboard.flight_log import read_jsonl
from nac_onboard.node.mpi_build import mpi_build
from tests.conftest import SHARED_DATA, free_port
from tests.integration.agents import agent_toml, kind, wait_for_record
from tests.integration.logs import first_record, records_logged

NAC_ONBOARD = str(Path(sys.executable).parent / "nac-onboard")


def nac_onboard(*args, timeout_s=60.0):
    return subprocess.run([NAC_ONBOARD, *args], capture_output=True, text=True, timeout=timeout_s)


def test_the_hostfile_comes_from_the_agents_and_the_job_runs_over_it(start_agent, tmp_path):
    ports = [free_port(), free_port()]
    configs = [agent_toml(name, role, k + 1, f"udpin:127.0.0.1:{free_port()}", tmp_path / "runs", ports[k],
                          [ports[1 - k]]) for k, (name, role) in enumerate([("uav1", "master"), ("uav2", "worker")])]
    for k, text in enumerate(configs):
        start_agent(text, name=f"uav{k + 1}")
    started = wait_for_record(tmp_path / "runs" / "test" / "uav1" / "agent.jsonl", kind("agent_started"))
    assert started["mpi_build"] == mpi_build()
    feed = configs[0].split("[state_feed]\nlisten = ")[1].split("\n")[0].strip('"')
    wait_for_record(tmp_path / "runs" / "test" / "uav1" / "agent.jsonl", kind("peer_seen", peer="uav2"))
    assert fetch_state(feed)["peers"]["uav2"]["mpi_build"] == mpi_build(), "the worker reports its build"

    done = nac_onboard("mpi", "hostfile", "--feed", feed)
    assert done.returncode == 0, done.stderr
    assert [line for line in done.stdout.splitlines() if not line.startswith("#")] == ["127.0.0.1:1"] * 2
    assert f"# rank 1: uav2 (worker, {mpi_build()})" in done.stdout

    hostfile = tmp_path / "hostfile"
    program = "from mpi4py import MPI; c = MPI.COMM_WORLD; print(f'rank {c.Get_rank()} of {c.Get_size()}')"
    job = nac_onboard("mpi", "run", "--feed", feed, "--hostfile", str(hostfile), "--timeout", "60", "--",
                      sys.executable, "-c", program)
    assert job.returncode == 0, job.stderr
    # the two ranks' lines reach mpiexec's stdout interleaved in any order, even mid-line
    assert sorted(re.findall(r"rank \d of \d", job.stdout)) == ["rank 0 of 2", "rank 1 of 2"], job.stdout
    assert hostfile.read_text().count("127.0.0.1:1") == 2


def test_keep_going_starts_a_job_whose_master_was_killed_again_from_its_checkpoint(start_agent, tmp_path):
    """`mpi run --keep-going` over the agents (issue 29): the master rank SIGKILLed mid-run (a brown-out of the master's
    MPI process) ends that mpiexec; the supervisor starts the job again with --resume over the worker its agent
    hears, and the job ends at its iterations. The weights are uninterrupted gradient descent's: the steps after the
    last checkpoint (0.2 s) are taken again from it, the same steps, and none is lost."""
    ports = [free_port(), free_port()]
    configs = [agent_toml(name, role, k + 1, f"udpin:127.0.0.1:{free_port()}", tmp_path / "runs", ports[k],
                          [ports[1 - k]]) for k, (name, role) in enumerate([("uav1", "master"), ("uav2", "worker")])]
    for k, text in enumerate(configs):
        start_agent(text, name=f"uav{k + 1}")
    feed = configs[0].split("[state_feed]\nlisten = ")[1].split("\n")[0].strip('"')
    wait_for_record(tmp_path / "runs" / "test" / "uav1" / "agent.jsonl", kind("peer_seen", peer="uav2"))
    # long enough that the kill lands mid-run: 3,000 iterations took 0.8 s on this machine, and under load the
    # job once ended before the test saw its 20th iteration and killed it (ProcessLookupError)
    out, total = tmp_path / "compute", 12000
    job = subprocess.Popen([NAC_ONBOARD, "mpi", "run", "--keep-going", "--feed", feed, "--hostfile",
                            str(tmp_path / "hostfile"), "--timeout", "120", "--", NAC_ONBOARD, "compute", "--task",
                            "linreg", "--iterations", str(total), "--out", str(out), "--emulate", "none",
                            "--checkpoint-s", "0.2", "--data", str(SHARED_DATA / "forestfires.csv")],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while not ((out / "results.npz").exists() and records_logged(out / "compute.jsonl", "iteration") > 20):
            assert time.monotonic() < deadline and job.poll() is None, "the job should be running"
            time.sleep(0.05)
        os.kill(first_record(out / "compute.jsonl", "run_started")["pid"], signal.SIGKILL)
        _, stderr = job.communicate(timeout=120)
    finally:
        if job.poll() is None:
            os.killpg(job.pid, signal.SIGKILL)
            job.wait()
    assert job.returncode == 0, stderr[-2000:]
    launches = read_jsonl(out / "job.jsonl").of_kind("job_launched")
    assert [(r["why"], r["workers"], r["resume"]) for r in launches] == [
        ("start", ["uav2"], False), ("ended without its summary", ["uav2"], True)]
    compute = read_jsonl(out / "compute.jsonl")
    assert compute.of_kind("resumed")[0]["iteration"] == launches[1]["from_iteration"] > 0
    assert compute.of_kind("run_summary")[-1]["iterations"] == total
    x, y = forestfires.load(SHARED_DATA / "forestfires.csv")
    w, _ = kernels.gradient_descent(x, y, np.zeros(x.shape[1]), 0.05, total)
    assert np.allclose(np.load(out / "results.npz")["weights"], w, rtol=1e-9, atol=1e-12)


def test_a_node_with_another_mpi_build_stops_the_job_before_it_starts(tmp_path):
    """A fake master's state feed (a real UDP socket) with two workers, one on Open MPI."""
    answer = {"t_s": 0.0, "self": {"id": "m", "role": "master", "mpi_build": mpi_build()},
              "peers": {"w1": {"id": "w1", "role": "worker", "host": "127.0.0.1", "lost": False,
                               "mpi_build": mpi_build()},
                        "w2": {"id": "w2", "role": "worker", "host": "127.0.0.2", "lost": False,
                               "mpi_build": "Open MPI 4.1.2"}}}
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as feed:
        feed.bind(("127.0.0.1", 0))
        feed.settimeout(20.0)

        def serve():
            try:
                for _ in range(2):
                    _, sender = feed.recvfrom(256)
                    feed.sendto(json.dumps(answer).encode(), sender)
            except OSError:
                pass

        threading.Thread(target=serve, daemon=True).start()
        address = f"127.0.0.1:{feed.getsockname()[1]}"
        done = nac_onboard("mpi", "hostfile", "--feed", address)
        assert done.returncode == 2 and done.stdout == ""
        assert "w2 (127.0.0.2) runs 'Open MPI 4.1.2'" in done.stderr and "w1" not in done.stderr
        hostfile = tmp_path / "hostfile"
        job = nac_onboard("mpi", "run", "--feed", address, "--hostfile", str(hostfile), "--", "true")
        assert job.returncode == 2 and "w2 (127.0.0.2)" in job.stderr
        assert not hostfile.exists(), "nothing started"


def test_doctor_names_a_missing_serial_port_and_passes_without_one(tmp_path):
    config = tmp_path / "agent.toml"
    config.write_text(agent_toml("uav1", "worker", 2, "serial:/dev/ttyNAC-missing:921600", tmp_path / "runs",
                                 free_port(), []))
    done = nac_onboard("doctor", "--config", str(config))
    assert done.returncode == 1
    assert "MISSING: autopilot serial port: /dev/ttyNAC-missing does not exist" in done.stdout
    assert f"mpi:    {mpi_build()}" in done.stdout and "glibc" in done.stdout
    done = nac_onboard("doctor", "--role", "master", "--json")
    assert done.returncode == 0, done.stdout
    report = json.loads(done.stdout)
    assert report["facts"]["mpi_build"] == mpi_build() and report["facts"]["mpiexec"]
    assert not [f for f in report["findings"] if f["needed"]]
