#!/usr/bin/env bash
# Install the NAC onboard agent as a systemd service on a UAV's companion (Jetson: aarch64, Ubuntu).
# Idempotent: run it again after `git pull` to upgrade; an existing /etc/nac/agent.toml is kept.
#
#   sudo deploy/install.sh --role master|worker --id NAME [--sysid N] [--uri URI]
#   deploy/install.sh --prefix DIR ...      stage everything under DIR (an image root, or a test) and touch
#                                           nothing outside it: no apt, no service start
#   deploy/install.sh --plan                say which Python and MPI this machine gets, change nothing
# Options:
#   --role master|worker   which example config to start from (deploy/master.toml, deploy/worker.toml)
#   --id NAME              the vehicle's name in logs and peer tables (default: the role)
#   --sysid N              the autopilot's MAVLink system id (default: the example's)
#   --uri URI              autopilot endpoint (default: serial:/dev/ttyTHS2:921600)
#   --force-config         overwrite an existing agent.toml (the old one is kept as agent.toml.bak)
#   --fleet-key FILE       the fleet's peer key (the same on every vehicle); without it one is made once
#   --no-system-packages   skip apt-get (iperf3, python3-venv) even without --prefix
#   --offline DIR          install from a wheelhouse made by deploy/wheelhouse.sh: no network at all
# Paths: Python >= 3.10 present: a venv on it; older (JetPack 4: 3.6): a standalone CPython 3.11 (runs on
# glibc 2.17+; from DIR/python/ offline, else through uv). MPI: the mpich wheel on glibc >= 2.28; older
# (JetPack 4: 2.27): the distribution's MPICH, with mpi4py compiled against it.
set -euo pipefail

usage() { sed -n '2,23p' "$0" | sed 's/^# \{0,1\}//'; exit 2; }
die() { echo "install.sh: $*" >&2; exit 2; }

here=$(cd "$(dirname "$0")" && pwd)
source_dir=$(dirname "$here")
prefix="" role="" vehicle_id="" sysid="" uri="" force_config=0 system_packages=1 fleet_key="" offline="" plan=0
while [ $# -gt 0 ]; do
    case "$1" in
        --prefix) prefix=${2%/}; shift 2 ;;
        --role) role=$2; shift 2 ;;
        --id) vehicle_id=$2; shift 2 ;;
        --sysid) sysid=$2; shift 2 ;;
        --uri) uri=$2; shift 2 ;;
        --force-config) force_config=1; shift ;;
        --fleet-key) fleet_key=$2; shift 2 ;;
        --no-system-packages) system_packages=0; shift ;;
        --offline) offline=${2%/}; shift 2 ;;
        --plan) plan=1; shift ;;
        -h|--help) usage ;;
        *) die "unknown option $1 (see --help)" ;;
    esac
done

# ---- the path: which Python and which MPI this machine can take -------------------------------------------
python=${PYTHON:-python3}
version_at_least() { [ "$(printf '%s\n%s\n' "$2" "$1" | sort -V | head -n 1)" = "$2" ]; }  # $1 >= $2
system_python=$("$python" -c 'import sys; print("%d.%d.%d" % sys.version_info[:3])' 2>/dev/null || echo none)
glibc=$(getconf GNU_LIBC_VERSION 2>/dev/null | awk '{print $2}')
glibc=${glibc:-unknown}
if [ "$system_python" != none ] && version_at_least "$system_python" 3.10; then
    python_path=system
    python_why="Python $system_python ($python): a venv on it"
else
    python_path=standalone
    python_why="standalone CPython 3.11 (the system's Python is $system_python, older than 3.10)"
fi
if [ "$glibc" != unknown ] && version_at_least "$glibc" 2.28; then
    mpi_path=wheel
    mpi_why="the mpich wheel (glibc $glibc >= 2.28)"
else
    mpi_path=distro
    mpi_why="the distribution's MPICH (apt: mpich libmpich-dev), mpi4py compiled against it (glibc $glibc < 2.28: no mpich wheel)"
fi
echo "install.sh: this machine: $(uname -m), glibc $glibc, Python $system_python"
echo "install.sh: Python: $python_why"
echo "install.sh: MPI: $mpi_why"
echo "install.sh: packages: ${offline:+from the wheelhouse $offline (offline)}${offline:-from the package index}"
[ "$plan" = 1 ] && exit 0
if [ -n "$offline" ]; then
    [ -d "$offline" ] || die "--offline $offline: no such directory (make it with deploy/wheelhouse.sh)"
    ls "$offline"/nac-*.whl >/dev/null 2>&1 || die "--offline $offline: no nac-*.whl in it: not a wheelhouse from deploy/wheelhouse.sh"
    manifest() { sed -n "s/^$1: //p" "$offline/MANIFEST.txt" 2>/dev/null; }
    [ "$(manifest platform)" = "$(uname -m)" ] \
        || die "--offline $offline: made for '$(manifest platform)', this machine is $(uname -m)"
    [ "$glibc" = unknown ] || version_at_least "$glibc" "$(manifest glibc)" \
        || die "--offline $offline: made for glibc $(manifest glibc), this machine has $glibc (wheelhouse.sh --glibc $glibc)"
    venv_python=3.11
    [ "$python_path" = system ] && venv_python=${system_python%.*}
    [ "$(manifest python)" = "$venv_python" ] \
        || die "--offline $offline: made for Python $(manifest python), the venv here runs $venv_python (wheelhouse.sh --python $venv_python)"
    if [ "$mpi_path" = wheel ] && ! ls "$offline"/mpich-*.whl >/dev/null 2>&1; then
        die "--offline $offline: no mpich wheel in it (made with --glibc below 2.28), but this machine takes one"
    fi
fi
case "$role" in master|worker) ;; *) die "--role must be master or worker" ;; esac
vehicle_id=${vehicle_id:-$role}
[[ "$vehicle_id" =~ ^[A-Za-z0-9._-]+$ ]] || die "--id must be letters, digits, '.', '_' or '-' (got '$vehicle_id')"
[ -z "$sysid" ] || [[ "$sysid" =~ ^[0-9]+$ ]] || die "--sysid must be a number (got '$sysid')"
if [ -n "$prefix" ]; then
    system_packages=0
    mkdir -p "$prefix"
    prefix=$(cd "$prefix" && pwd)
elif [ "$(id -u)" -ne 0 ]; then
    die "run as root (sudo), or stage into a directory with --prefix DIR"
fi

app=$prefix/opt/nac
venv=$app/venv
etc=$prefix/etc/nac
units=$prefix/etc/systemd/system
step() { echo "==> $*"; }

[ -n "$offline" ] && system_packages=0  # no network: apt cannot run (the JetPack image or a local mirror can)
if [ "$system_packages" = 1 ]; then
    packages="iperf3 openssh-client openssh-server chrony"
    [ "$python_path" = system ] && packages="$packages python3-venv python3-pip"
    [ "$mpi_path" = distro ] && packages="$packages mpich libmpich-dev"
    step "system packages: $packages (apt)"
    # shellcheck disable=SC2086
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q $packages >/dev/null
fi

step "user nac (group dialout for the autopilot's serial port)"
mkdir -p "$prefix/etc"
if [ -n "$prefix" ]; then
    systemd-sysusers --root="$prefix" "$here/nac.sysusers.conf"
else
    systemd-sysusers "$here/nac.sysusers.conf"
fi

if [ "$python_path" = standalone ]; then
    # python-build-standalone's CPython: one tarball, runs on glibc 2.17+, what uv installs.
    if [ -n "$offline" ]; then
        if [ ! -x "$app/python/bin/python3" ]; then
            tarball=$(ls "$offline"/python/cpython-3.11*.tar.gz 2>/dev/null | head -n 1)
            [ -n "$tarball" ] || die "--offline $offline: no python/cpython-3.11*.tar.gz in it (wheelhouse.sh --standalone-python FILE)"
            step "standalone CPython 3.11 from $tarball into $app/python"
            mkdir -p "$app/python"
            tar -xzf "$tarball" -C "$app/python" --strip-components=1
        fi
        python=$app/python/bin/python3
    else
        step "standalone CPython 3.11 through uv into $app/python-uv"
        "$python" -m pip install -q --user --upgrade "pip<22" || die "cannot upgrade $python's pip"
        "$python" -m pip install -q --user uv || die "cannot install uv with $python's pip"
        UV_PYTHON_INSTALL_DIR="$app/python-uv" "$python" -m uv python install 3.11 \
            || die "uv could not fetch a standalone CPython 3.11 (no internet? use --offline)"
        python=$(ls -d "$app"/python-uv/cpython-3.11*/bin/python3 | head -n 1)
    fi
fi

step "python environment $venv"
if [ ! -x "$venv/bin/python" ]; then
    "$python" -c "import ensurepip, venv" 2>/dev/null \
        || die "$python cannot make a venv: install python3-venv (apt-get install python3-venv)"
    "$python" -m venv "$venv"
fi
pip_install() {
    if [ -n "$offline" ]; then
        "$venv/bin/python" -m pip install -q --disable-pip-version-check --no-index --find-links "$offline" "$@"
    else
        "$venv/bin/python" -m pip install -q --disable-pip-version-check "$@"
    fi
}
if [ "$mpi_path" = distro ]; then
    command -v mpicc >/dev/null || die "no mpicc: install the distribution's MPICH (apt-get install mpich libmpich-dev)"
    # mpi4py compiled against that MPICH, so every rank links the library mpiexec comes with.
    MPICC=mpicc pip_install --no-binary mpi4py mpi4py
    extra=""
else
    extra="[mpich]"
fi
if [ -n "$offline" ]; then
    pip_install --upgrade "$(ls "$offline"/nac-*.whl | head -n 1)$extra"
else
    pip_install --upgrade "$source_dir$extra"
fi
mkdir -p "$app/deploy"
cp "$here/README.md" "$here/master.toml" "$here/worker.toml" "$app/deploy/"
cp -r "$here/mpi" "$app/deploy/"

step "config $etc/agent.toml"
mkdir -p "$etc"
if [ -n "$fleet_key" ]; then
    [ -s "$fleet_key" ] || die "--fleet-key $fleet_key: no such file, or empty"
    install -m 0640 "$fleet_key" "$etc/fleet.key"
elif [ ! -s "$etc/fleet.key" ]; then
    (umask 027 && "$venv/bin/python" -c "import secrets; print(secrets.token_hex(32))" > "$etc/fleet.key")
    echo "    made a new fleet key $etc/fleet.key: copy this same file to every vehicle (--fleet-key FILE)"
fi
chgrp "$(awk -F: '$1 == "nac" {print $4}' "$prefix/etc/passwd")" "$etc/fleet.key" 2>/dev/null || true
if [ -f "$etc/agent.toml" ] && [ "$force_config" = 0 ]; then
    echo "    kept the existing config (use --force-config to replace it)"
else
    [ -f "$etc/agent.toml" ] && cp "$etc/agent.toml" "$etc/agent.toml.bak"
    sed -e "s/^id = .*/id = \"$vehicle_id\"/" \
        -e "${sysid:+s/^sysid = [0-9]*/sysid = $sysid/}" \
        -e "${uri:+s|^uri = \"[^\"]*\"|uri = \"$uri\"|}" \
        "$here/$role.toml" > "$etc/agent.toml.new"
    "$venv/bin/python" - "$etc/agent.toml.new" <<'EOF'
import sys
from nac_onboard.agent.config import ConfigError, load_agent_config
try:
    load_agent_config(sys.argv[1])
except ConfigError as err:
    sys.exit(f"install.sh: the written config is not valid: {err}")
EOF
    mv "$etc/agent.toml.new" "$etc/agent.toml"
fi
[ "$role" = master ] && cp -n "$here/mpi/hostfile.template" "$etc/mpi-hostfile" 2>/dev/null || true

step "systemd unit $units/nac-onboard.service"
mkdir -p "$units" "$prefix/var/log/nac" "$prefix/var/lib/nac"
install -m 0644 "$here/nac-onboard.service" "$units/nac-onboard.service"
if [ -n "$prefix" ]; then
    systemctl --root="$prefix" enable nac-onboard.service
    owner=$(awk -F: '$1 == "nac" {print $3 ":" $4}' "$prefix/etc/passwd")
    chown "$owner" "$prefix/var/log/nac" "$prefix/var/lib/nac" 2>/dev/null || true  # needs root; harmless if not
else
    chown nac:nac /var/log/nac /var/lib/nac
    systemctl daemon-reload
    systemctl enable nac-onboard.service
    systemctl restart nac-onboard.service
    systemctl --no-pager --lines=0 status nac-onboard.service || true
fi
step "done: $vehicle_id ($role); logs under $prefix/var/log/nac"
