#!/usr/bin/env bash
# Install the NAC onboard agent as a systemd service on a UAV's companion (Jetson TX2: aarch64, Ubuntu).
# Idempotent: run it again after `git pull` to upgrade; an existing /etc/nac/agent.toml is kept.
#
#   sudo deploy/install.sh --role master|worker --id NAME [--sysid N] [--uri URI]
#   deploy/install.sh --prefix DIR ...      stage everything under DIR (an image root, or a test) and touch
#                                           nothing outside it: no apt, no service start
# Options:
#   --role master|worker   which example config to start from (deploy/master.toml, deploy/worker.toml)
#   --id NAME              the vehicle's name in logs and peer tables (default: the role)
#   --sysid N              the autopilot's MAVLink system id (default: the example's)
#   --uri URI              autopilot endpoint (default: serial:/dev/ttyTHS2:921600)
#   --force-config         overwrite an existing agent.toml (the old one is kept as agent.toml.bak)
#   --fleet-key FILE       the fleet's peer key (the same on every vehicle); without it one is made once
#   --no-system-packages   skip apt-get (iperf3, python3-venv) even without --prefix
set -euo pipefail

usage() { sed -n '2,17p' "$0" | sed 's/^# \{0,1\}//'; exit 2; }
die() { echo "install.sh: $*" >&2; exit 2; }

here=$(cd "$(dirname "$0")" && pwd)
source_dir=$(dirname "$here")
prefix="" role="" vehicle_id="" sysid="" uri="" force_config=0 system_packages=1 fleet_key=""
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
        -h|--help) usage ;;
        *) die "unknown option $1 (see --help)" ;;
    esac
done
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
python=${PYTHON:-python3}
step() { echo "==> $*"; }

if [ "$system_packages" = 1 ]; then
    step "system packages: iperf3, python3-venv, openssh (apt)"
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q iperf3 python3-venv python3-pip openssh-client \
        openssh-server >/dev/null
fi

step "user nac (group dialout for the autopilot's serial port)"
mkdir -p "$prefix/etc"
if [ -n "$prefix" ]; then
    systemd-sysusers --root="$prefix" "$here/nac.sysusers.conf"
else
    systemd-sysusers "$here/nac.sysusers.conf"
fi

step "python environment $venv"
[ -x "$venv/bin/python" ] || "$python" -m venv "$venv"
"$venv/bin/python" -m pip install -q --disable-pip-version-check --upgrade "$source_dir"
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
