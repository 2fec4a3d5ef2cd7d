"""deploy/: install.sh staged into a scratch root, and systemd's own verifier on the installed unit."""

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from nac_onboard.agent.config import load_agent_config

# pip downloading and unpacking for a minute, with minutes of timeout: beside the exclusive tests (make test)
pytestmark = pytest.mark.niced
DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
HOST_UNITS = Path("/usr/lib/systemd/system")
needs_systemd = pytest.mark.skipif(not (shutil.which("systemd-analyze") and shutil.which("systemd-sysusers")
                                        and HOST_UNITS.is_dir()),
                                   reason="systemd tools not installed (.ci/run installs them)")


def install(root: Path, *args: str, offline: Path | None = None) -> subprocess.CompletedProcess:
    """install.sh as an operator runs it, except that pip does not byte-compile the venv (PIP_COMPILE=0): that is
    half of the install's time here, and what these tests check is the layout, the unit and the config. Offline:
    from that wheelhouse, in a network namespace with no interface up, so pip can reach no index at all."""
    command = ["bash", str(DEPLOY / "install.sh"), "--prefix", str(root), *args]
    if offline is not None:
        command = ["unshare", "--net", *command, "--offline", str(offline)]
    return subprocess.run(command, capture_output=True, text=True, timeout=300, env=dict(os.environ, PIP_COMPILE="0"))


def wheelhouse(out: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(DEPLOY / "wheelhouse.sh"), "--out", str(out), *args], capture_output=True,
                          text=True, timeout=600)


def verify(root: Path, unit: Path) -> subprocess.CompletedProcess:
    return subprocess.run(["systemd-analyze", "verify", f"--root={root}", str(unit)], capture_output=True,
                          text=True, timeout=60)


@pytest.mark.slow
@needs_systemd
def test_an_offline_install_into_a_scratch_root_is_complete_idempotent_and_verified(tmp_path):
    """The wheelhouse this machine's companions would take (its contents checked), then install.sh --offline from
    it with no network, twice: the layout, the unit under systemd's verifier, the config kept the second time."""
    machine = os.uname().machine
    made = wheelhouse(tmp_path / "wh", "--platform", machine, "--python", "3.11")
    assert made.returncode == 0, made.stderr
    files = sorted(p.name for p in (tmp_path / "wh").iterdir())
    wheels = [f for f in files if f.endswith(".whl")]
    names = {w.split("-")[0].lower() for w in wheels}
    assert {"nac", "numpy", "pandas", "pymavlink", "mpi4py", "mpich", "aiohttp", "setuptools", "build"} <= names
    assert any(f.startswith("mpi4py-") and f.endswith(".tar.gz") for f in files), "mpi4py's source, to compile"
    for wheel in wheels:
        python_tag, abi, platform = wheel.removesuffix(".whl").split("-")[-3:]
        assert platform == "any" or machine in platform, wheel
        assert abi in ("none", "abi3", "cp311") and ("cp311" in python_tag or python_tag.startswith("py")), wheel
    checked = subprocess.run(["sha256sum", "--check", "--quiet", "SHA256SUMS"], cwd=tmp_path / "wh",
                             capture_output=True, text=True, timeout=60)
    assert checked.returncode == 0, checked.stdout

    root = tmp_path / "root"
    first = install(root, "--role", "worker", "--id", "uav2", "--sysid", "2", "--uri", "udpin:0.0.0.0:14561",
                    offline=tmp_path / "wh")
    assert first.returncode == 0, first.stdout + first.stderr
    assert "from the wheelhouse" in first.stdout and "the mpich wheel" in first.stdout
    venv = root / "opt/nac/venv/bin"
    assert (venv / "mpiexec").exists(), "the mpich wheel's mpiexec"
    doctor = subprocess.run([str(venv / "nac-onboard"), "doctor", "--role", "master"], capture_output=True,
                            text=True, timeout=60)
    assert doctor.returncode == 0 and "mpi:    MPICH" in doctor.stdout, doctor.stdout + doctor.stderr

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
    second = install(root, "--role", "worker", "--id", "uav2", offline=tmp_path / "wh")
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


def fake_machine(folder: Path, python_version: str | None, glibc: str) -> dict:
    """PATH with a python3 that says it is python_version (None: no Python at all) and a getconf that says glibc."""
    folder.mkdir()
    says = "exit 127" if python_version is None else f"echo {python_version}"
    (folder / "python3").write_text(f"#!/bin/sh\n{says}\n")
    (folder / "getconf").write_text(f"#!/bin/sh\n[ \"$1\" = GNU_LIBC_VERSION ] && echo 'glibc {glibc}'\n")
    for tool in folder.iterdir():
        tool.chmod(0o755)
    env = {k: v for k, v in os.environ.items() if k != "PYTHON"}
    return dict(env, PATH=f"{folder}:/usr/bin:/bin")


@pytest.mark.parametrize("python_version, glibc, python_path, mpi_path", [
    ("3.6.9", "2.27", "standalone CPython 3.11", "distribution's MPICH"),  # Jetson TX2/Nano, JetPack 4.6
    ("3.8.10", "2.31", "standalone CPython 3.11", "mpich wheel"),  # Xavier/Orin, JetPack 5 (Ubuntu 20.04)
    ("3.10.12", "2.35", "a venv on it", "mpich wheel"),  # Orin, JetPack 6 (Ubuntu 22.04)
    ("3.11.2", "2.36", "a venv on it", "mpich wheel"),  # Debian 12, a Raspberry Pi or a laptop
    ("3.12.3", "2.27", "a venv on it", "distribution's MPICH"),  # a newer Python on an old glibc
    (None, "2.28", "standalone CPython 3.11", "mpich wheel"),  # no Python at all
])
def test_install_says_which_python_and_mpi_this_machine_takes(tmp_path, python_version, glibc, python_path,
                                                             mpi_path):
    env = fake_machine(tmp_path / "bin", python_version, glibc)
    done = subprocess.run(["bash", str(DEPLOY / "install.sh"), "--plan"], capture_output=True, text=True,
                          timeout=30, env=env)
    assert done.returncode == 0, done.stderr
    lines = dict(line.removeprefix("install.sh: ").split(": ", 1) for line in done.stdout.splitlines())
    assert python_path in lines["Python"] and mpi_path in lines["MPI"]
    assert f"glibc {glibc}" in lines["this machine"] and f"Python {python_version or 'none'}" in lines["this machine"]


def test_an_offline_install_refuses_a_wheelhouse_made_for_another_machine(tmp_path):
    wheelhouse = tmp_path / "wh"
    wheelhouse.mkdir()
    (wheelhouse / "nac-0.1.0-py3-none-any.whl").write_bytes(b"")
    machine = os.uname().machine
    other = "aarch64" if machine == "x86_64" else "x86_64"
    env = fake_machine(tmp_path / "bin", "3.11.2", "2.36")
    for manifest, message in [(f"platform: {other}\npython: 3.11\nglibc: 2.28\n", f"made for '{other}'"),
                              (f"platform: {machine}\npython: 3.10\nglibc: 2.28\n", "made for Python 3.10"),
                              (f"platform: {machine}\npython: 3.11\nglibc: 2.39\n", "made for glibc 2.39"),
                              (f"platform: {machine}\npython: 3.11\nglibc: 2.27\n", "no mpich wheel")]:
        (wheelhouse / "MANIFEST.txt").write_text(manifest)
        done = subprocess.run(["bash", str(DEPLOY / "install.sh"), "--offline", str(wheelhouse), "--prefix",
                               str(tmp_path / "root"), "--role", "worker"], capture_output=True, text=True,
                              timeout=30, env=env)
        assert done.returncode == 2 and message in done.stderr, done.stderr
    assert not (tmp_path / "root" / "opt").exists(), "refused before touching anything"


def test_a_jetpack4_wheelhouse_asks_only_for_what_glibc_2_27_runs_and_leaves_mpich_out(tmp_path):
    """What wheelhouse.sh would download for a TX2 (aarch64, glibc 2.27), without downloading: manylinux tags up
    to 2.27 and no mpich (the real download, for this machine, is in the test above; for aarch64 with mpich, in
    `make arm64-check`)."""
    made = wheelhouse(tmp_path / "wh", "--platform", "aarch64", "--python", "3.11", "--glibc", "2.27", "--dry-run")
    assert made.returncode == 0, made.stderr
    requirements = (tmp_path / "wh" / "requirements.txt").read_text().splitlines()
    assert any(r.startswith("mpi4py") for r in requirements) and not any(r.startswith("mpich") for r in requirements)
    tags = re.findall(r"--platform (\S+)", made.stdout)
    assert "manylinux_2_27_aarch64" in tags and "manylinux_2_17_aarch64" in tags and "manylinux2014_aarch64" in tags
    assert not [t for t in tags if t.startswith("manylinux_2_") and int(t.split("_")[2]) > 27], tags
    assert "--python-version 3.11 --abi cp311" in made.stdout
    assert not [f for f in (tmp_path / "wh").iterdir() if f.suffix in (".whl", ".gz")], "nothing downloaded"
    bad = wheelhouse(tmp_path / "bad", "--platform", "arm", "--python", "3.11")
    assert bad.returncode == 2 and "--platform must be aarch64 or x86_64" in bad.stderr
