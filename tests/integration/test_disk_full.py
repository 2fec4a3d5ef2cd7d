"""A full disk under the agent: logging stops, everything else goes on, and the log resumes with a record of what
was lost (it once exited on ENOSPC, and systemd restarted it into the same failure). A full disk under the MPI
job's checkpoint: that checkpoint is skipped, training goes on."""

import os
import signal
import subprocess
import time

import numpy as np
import pytest

from nac_onboard.agent.state_feed import fetch_state
from nac_onboard.child_process import process_running
from nac_onboard.compute import forestfires
from nac_onboard.flight_log import RETRY_S, read_jsonl
from tests.conftest import free_port
from tests.integration.agents import agent_toml, kind, wait_for_record
from tests.integration.test_agent import companion_uri
from tests.integration.test_compute import iterations_logged, job
from tests.integration.test_compute import wait_until as wait_job

needs_root = pytest.mark.skipif(os.geteuid() != 0, reason="mounting a small tmpfs needs root (CI runs as root)")


@pytest.fixture
def small_disk(tmp_path):
    disk = tmp_path / "disk"
    disk.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=512k", "tmpfs", str(disk)], check=True, timeout=10)
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], timeout=10)


def fill(disk) -> None:
    """Take every free byte of the disk; called again, what was freed since (it appends)."""
    fd = os.open(disk / "filler", os.O_WRONLY | os.O_CREAT | os.O_APPEND)
    try:
        while True:
            os.write(fd, b"\0" * 4096)
    except OSError:
        pass
    finally:
        os.close(fd)


def wait_until(condition, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"{what} within {timeout_s:g} s"
        time.sleep(0.05)


@needs_root
def test_the_agent_keeps_working_on_a_full_disk_and_logs_the_gap_afterwards(start_sitl, start_agent, small_disk):
    sim = start_sitl(speedup=5.0)
    feed = f"127.0.0.1:{free_port()}"
    agent = start_agent(agent_toml("uav1", "master", 1, companion_uri(sim, 0), small_disk / "runs", free_port(), [],
                                   state_feed={"listen": feed}))
    log_path = small_disk / "runs" / "test" / "uav1" / "agent.jsonl"
    wait_for_record(log_path, kind("link_up"))
    fill(small_disk)
    wait_until(lambda: "cannot write" in agent.stderr_text(), 20.0, "the agent reports the full disk once")
    before = fetch_state(feed)["t_s"]
    wait_until(lambda: fetch_state(feed)["t_s"] > before + 1.0, 10.0, "the state feed still answers, up to date")
    assert agent.alive() and fetch_state(feed)["self"]["link_up"]
    assert agent.stderr_text().count("cannot write") <= 3, "reported once per file, not per record"

    (small_disk / "filler").unlink()
    gap = wait_for_record(log_path, kind("log_gap"), timeout_s=RETRY_S + 10.0)
    assert gap["records_lost"] > 0 and gap["bytes_lost"] > 0 and gap["error"].startswith("ENOSPC")
    assert gap["since_s"] < gap["t_s"]
    assert agent.stop() == 0
    read = read_jsonl(log_path)
    assert len(read.problems) <= 1, read.problems  # at most the one record the disk cut in half
    assert read.records[-1]["kind"] == "agent_stopped"


@needs_root
def test_a_checkpoint_into_a_full_disk_is_skipped_and_training_goes_on(small_disk, tmp_path):
    """The master's checkpoint (np.savez) on a full disk once aborted the whole job and left a 0-byte partial file:
    now the partial file is removed, the last whole checkpoint stays, a checkpoint_failed record says so, training
    goes on, and the next checkpoint after the disk has room again is written. The job's logs are kept off the small
    disk (symlinks to tmp_path) so the record of the failure can be read while the disk is full."""
    out = small_disk / "compute"
    out.mkdir()
    for name in ("compute.jsonl", "rank-1.jsonl", "rank-2.jsonl"):
        (out / name).symlink_to(tmp_path / name)
    results, partial = out / "results.npz", out / "results.npz.partial.npz"

    def failures() -> list[dict]:
        return read_jsonl(tmp_path / "compute.jsonl").of_kind("checkpoint_failed")

    with job("--task", "linreg", "--iterations", "1000000", "--out", str(out), "--checkpoint-s", "0.1") as proc:
        wait_job(lambda: results.exists() and iterations_logged(tmp_path) >= 5, proc)
        fill(small_disk)
        # taking again what a checkpoint's removed partial file frees: filled while a partial file held its pages,
        # the disk had room for the next checkpoint and each one after (a loaded CI run saw no second failure)
        wait_job(lambda: fill(small_disk) or len(failures()) >= 2, proc)
        failed = failures()
        assert all(f["error"].startswith("ENOSPC") for f in failed), failed
        kept = int(np.load(results)["iteration"])
        assert failed[-1]["kept_iteration"] == kept and failed[-1]["iteration"] > kept
        assert not partial.exists(), "the partial file is removed"
        before = iterations_logged(tmp_path)
        wait_job(lambda: iterations_logged(tmp_path) > before + 5, proc)  # training goes on

        (small_disk / "filler").unlink()
        wait_job(lambda: int(np.load(results)["iteration"]) > failed[-1]["iteration"], proc)
        assert proc.poll() is None
        # stopped as its supervisor stops it (SIGTERM: the last checkpoint written whole), not killed mid-write by
        # its proxy, which would leave a partial file whatever the disk (it checkpoints every 0.1 s)
        master, = read_jsonl(tmp_path / "compute.jsonl").of_kind("run_started")
        os.kill(master["pid"], signal.SIGTERM)
        wait_until(lambda: not process_running(master["pid"]), 30.0, "the master stops")
    checkpoint = np.load(results)
    assert checkpoint["weights"].shape == (len(forestfires.FEATURES),) and np.isfinite(checkpoint["weights"]).all()
    assert not partial.exists()
