#!/usr/bin/env bash
# Let the master's `nac` user start MPI ranks on the workers (MPICH's launcher uses ssh without a password).
# Run on the master as root, once, with the workers on the vehicle network and the agent installed on each
# (deploy/install.sh creates the nac user):
#     deploy/mpi/setup-ssh.sh [--admin USER] 192.168.1.11 192.168.1.12
# USER (default: the account that ran sudo) is an account on the workers that may use sudo; it is asked for its
# password once per worker to append the master's public key to nac's authorized_keys there.
set -euo pipefail
admin=${SUDO_USER:-}
if [ "${1:-}" = "--admin" ]; then admin=$2; shift 2; fi
if [ $# -eq 0 ] || [ -z "$admin" ]; then
    echo "usage: $0 [--admin USER] WORKER_HOST..." >&2
    exit 2
fi
home=$(getent passwd nac | cut -d: -f6)
[ -n "$home" ] || { echo "no user nac on this machine: run deploy/install.sh first" >&2; exit 1; }
install -d -m 0700 -o nac -g nac "$home/.ssh"
[ -f "$home/.ssh/id_ed25519" ] || sudo -u nac ssh-keygen -q -t ed25519 -N "" -f "$home/.ssh/id_ed25519"
for host in "$@"; do
    grep -q "^$host " "$home/.ssh/known_hosts" 2>/dev/null \
        || ssh-keyscan -T 5 "$host" 2>/dev/null | sudo -u nac tee -a "$home/.ssh/known_hosts" >/dev/null
    key=$(cat "$home/.ssh/id_ed25519.pub")
    # -t: sudo on the worker may ask for the admin's password.
    ssh -t "$admin@$host" "h=\$(getent passwd nac | cut -d: -f6) && sudo install -d -m 0700 -o nac -g nac \$h/.ssh &&
        (sudo grep -qxF '$key' \$h/.ssh/authorized_keys 2>/dev/null || echo '$key' | sudo tee -a \$h/.ssh/authorized_keys >/dev/null) &&
        sudo chown nac:nac \$h/.ssh/authorized_keys && sudo chmod 0600 \$h/.ssh/authorized_keys"
    sudo -u nac ssh -o BatchMode=yes "nac@$host" true && echo "ok: nac@$host accepts the master's key"
done
