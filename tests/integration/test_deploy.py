"""deploy/: install.sh staged into a scratch root, and systemd's own verifier on the installed unit."""

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from nac_onboard.agent.config import load_agent_config

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
HOST_UNITS = Path("/usr/lib/systemd/system")
needs_systemd = pytest.mark.skipif(not (shutil.which("systemd-analyze") and shutil.which("systemd-sysusers")
                                        and HOST_UNITS.is_dir()),
                                   reason="systemd tools not installed (.ci/run installs them)")


def install(root: Path, *args: str) -> subprocess.CompletedProcess:
    """install.sh as an operator runs it, except that pip does not byte-compile the venv (PIP_COMPILE=0): that is
    half of the install's time here, and what these tests check is the layout, the unit and the config."""
    return subprocess.run(["bash", str(DEPLOY / "install.sh"), "--prefix", str(root), *args],
                          capture_output=True, text=True, timeout=300, env=dict(os.environ, PIP_COMPILE="0"))


def verify(root: Path, unit: Path) -> subprocess.CompletedProcess:
    return subprocess.run(["systemd-analyze", "verify", f"--root={root}", str(unit)], capture_output=True,
                          text=True, timeout=60)


@pytest.mark.slow
@needs_systemd
def test_install_into_a_scratch_root_is_complete_idempotent_and_verified(tmp_path):
    root = tmp_path / "root"
    first = install(root, "--role", "worker", "--id", "uav2", "--sysid", "2", "--uri", "udpin:0.0.0.0:14561")
    assert first.returncode == 0, first.stderr

    config = load_agent_config(root / "etc/nac/agent.toml")
    assert (config.vehicle.id, config.vehicle.role, config.vehicle.sysid) == ("uav2", "worker", 2)
    assert config.autopilot.uri == "udpin:0.0.0.0:14561"
    passwd = (root / "etc/passwd").read_text().splitlines()
    assert [line.split(":")[0] for line in passwd].count("nac") == 1
    dialout = next(line for line in (root / "etc/group").read_text().splitlines() if line.startswith("dialout:"))
    assert "nac" in dialout.split(":")[3].split(",")
    unit = root / "etc/systemd/system/nac-onboard.service"
    assert unit.read_bytes() == (DEPLOY / "nac-onboard.service").read_bytes()
    assert (root / "etc/systemd/system/multi-user.target.wants/nac-onboard.service").is_symlink()
    agent = root / "opt/nac/venv/bin/nac-onboard"
    ran = subprocess.run([str(agent), "log", "check", str(root / "etc/nac/agent.toml")], capture_output=True,
                         text=True, timeout=60)
    assert "not a log record" in ran.stdout, "the installed command runs (and reads a non-log as one)"

    # systemd's verifier, on the unit as installed: ExecStart must exist in the root, directives must parse.
    shutil.copytree(HOST_UNITS, root / "usr/lib/systemd/system", symlinks=True)
    checked = verify(root, unit)
    assert checked.returncode == 0 and checked.stdout + checked.stderr == "", checked.stderr
    broken = root / "etc/systemd/system/broken.service"
    broken.write_text(unit.read_text().replace("/opt/nac/venv/bin/nac-onboard", "/opt/nac/venv/bin/missing"))
    assert verify(root, broken).returncode != 0, "the verifier does look at ExecStart"
    broken.unlink()

    # Again, over a config the operator edited: same result, the edit kept.
    edited = (root / "etc/nac/agent.toml").read_text().replace("rate_hz = 2.0", "rate_hz = 5.0")
    (root / "etc/nac/agent.toml").write_text(edited)
    second = install(root, "--role", "worker", "--id", "uav2")
    assert second.returncode == 0, second.stderr
    assert "kept the existing config" in second.stdout
    assert (root / "etc/nac/agent.toml").read_text() == edited
    assert (root / "etc/passwd").read_text().splitlines() == passwd


def test_install_refuses_bad_arguments_before_touching_anything(tmp_path):
    root = tmp_path / "root"
    for args, message in [(["--role", "boss"], "--role must be master or worker"),
                          (["--role", "worker", "--id", "uav 2"], "--id must be"),
                          (["--role", "worker", "--sysid", "two"], "--sysid must be a number"),
                          (["--role", "worker", "--colour", "red"], "unknown option --colour")]:
        result = install(root, *args)
        assert result.returncode == 2 and message in result.stderr
    assert not (root / "opt").exists()
