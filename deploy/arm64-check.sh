#!/usr/bin/env bash
# NAC on an arm64 companion's userland, here: a Debian arm64 root (debootstrap from this machine's own Debian
# package source) run under qemu-user-static, where the offline path is taken as a field would take it:
#   wheelhouse.sh on this machine -> install.sh --offline inside the arm64 root with no network at all ->
#   nac-onboard doctor, nac-onboard agent --help, and a compute run of two ranks (the master and one worker).
# Every step is timed; the summary goes to stdout and to WORK/summary.md (recorded in docs/deploy-arm64.md).
#
#   sudo deploy/arm64-check.sh [--work DIR] [--keep]      (make arm64-check)
# Needs root, debootstrap, qemu-user-static (binfmt_misc is mounted and qemu-aarch64 enabled when it is not).
set -euo pipefail

die() { echo "arm64-check.sh: $*" >&2; exit 2; }
here=$(cd "$(dirname "$0")" && pwd)
source_dir=$(dirname "$here")
work=$source_dir/runs/arm64-check keep=0 suite=bookworm
while [ $# -gt 0 ]; do
    case "$1" in
        --work) work=${2%/}; shift 2 ;;
        --keep) keep=1; shift ;;
        -h|--help) sed -n '2,10p' "$0" | sed 's/^# \{0,1\}//'; exit 2 ;;
        *) die "unknown option $1" ;;
    esac
done
[ "$(id -u)" -eq 0 ] || die "run as root: debootstrap and chroot need it"
command -v debootstrap >/dev/null || die "no debootstrap (apt-get install debootstrap qemu-user-static binfmt-support)"
[ -x /usr/bin/qemu-aarch64-static ] || die "no qemu-aarch64-static (apt-get install qemu-user-static binfmt-support)"
if [ ! -e /proc/sys/fs/binfmt_misc/status ]; then
    mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc || die "cannot mount binfmt_misc"
fi
[ -e /proc/sys/fs/binfmt_misc/qemu-aarch64 ] || update-binfmts --enable qemu-aarch64 \
    || die "cannot enable qemu-aarch64 in binfmt_misc"
# The Debian package source this machine already uses (its apt configuration), so no address is built in here.
mirror=${MIRROR:-$(sed -n 's/^URIs: *\([^ ]*\).*/\1/p' /etc/apt/sources.list.d/*.sources 2>/dev/null | grep -v security | head -n 1)}
mirror=${mirror:-$(awk '$1 == "deb" && $0 !~ /security/ {print $2; exit}' /etc/apt/sources.list 2>/dev/null)}
[ -n "$mirror" ] || die "no Debian package source in /etc/apt: set MIRROR"

root=$work/root
mkdir -p "$work"
summary=$work/summary.md
: > "$summary"
timed() {  # timed "what" command...: run it, log its output, record its seconds
    local what=$1 start end; shift
    start=$(date +%s.%N)
    if "$@" > "$work/step.log" 2>&1; then
        end=$(date +%s.%N)
        printf '| %s | %.0f s | ok |\n' "$what" "$(echo "$end - $start" | bc)" | tee -a "$summary"
        cat "$work/step.log" >> "$work/all.log"
    else
        end=$(date +%s.%N)
        printf '| %s | %.0f s | FAILED |\n' "$what" "$(echo "$end - $start" | bc)" | tee -a "$summary"
        tail -n 30 "$work/step.log" >&2
        exit 1
    fi
}
# A command in the arm64 root, in namespaces of its own: no network but loopback (the install is offline), its
# own /proc, /sys and /dev/shm (MPI reads the first two and shares memory through the last), all gone when it
# ends.
inside() {
    unshare --net --mount --pid --fork /bin/sh -c '
        root=$1; shift
        ip link set lo up && mount -t proc proc "$root/proc" && mount -t sysfs sysfs "$root/sys" \
            && mkdir -p "$root/dev/shm" \
            && mount -t tmpfs tmpfs "$root/dev/shm" || exit 1
        exec chroot "$root" /usr/bin/env -i PATH=/usr/sbin:/usr/bin:/sbin:/bin HOME=/root LANG=C.UTF-8 "$@"
    ' inside "$root" "$@"
}

echo "| step | time | result |" | tee -a "$summary"
echo "| --- | ---: | --- |" | tee -a "$summary"
if [ ! -x "$root/usr/bin/python3" ]; then
    timed "debootstrap Debian $suite arm64 (python3, venv, systemd)" debootstrap --arch=arm64 --variant=minbase \
        --include=python3,python3-venv,systemd,procps "$suite" "$root" "$mirror"
fi
timed "wheelhouse.sh --platform aarch64 --python 3.11 (on this x86-64 machine)" \
    "$here/wheelhouse.sh" --platform aarch64 --python 3.11 --out "$work/wheelhouse"
rm -rf "$root/src" "$root/wheelhouse" "$root/stage"
mkdir -p "$root/src"
git -C "$source_dir" ls-files -z --cached --others --exclude-standard \
    | (cd "$source_dir" && xargs -0 cp --parents -t "$root/src")
cp -r "$work/wheelhouse" "$root/wheelhouse"
timed "install.sh --offline (arm64, no network)" inside /bin/bash -c \
    "cd /src && deploy/install.sh --offline /wheelhouse --prefix /stage --role worker --id arm1"
venv=/stage/opt/nac/venv/bin
inside "$venv/python" -c "import platform; print('arm64 root:', platform.machine(), platform.python_version())" \
    | tee -a "$work/all.log"
timed "nac-onboard doctor --role worker" inside "$venv/nac-onboard" doctor --role worker
sed 's/^/    /' "$work/step.log"
timed "nac-onboard agent --help" inside "$venv/nac-onboard" agent --help
# Two ranks on one emulated machine: qemu-user does not carry MPICH's shared-memory path between local ranks (they
# wait for ever), so they talk TCP over loopback through OFI, the path ranks on separate Jetsons take anyway.
timed "compute: mpiexec -n 2 nac-onboard compute --task matmul, 5 iterations (master + 1 worker)" inside /bin/bash -c \
    "cd /tmp && rm -rf /tmp/compute && export MPIR_CVAR_NOLOCAL=1 MPIR_CVAR_CH4_NETMOD=ofi FI_PROVIDER=tcp && $venv/mpiexec -n 2 $venv/nac-onboard compute --task matmul --iterations 5 --m 64 --n 64 --l 64 --timeout-s 120 --out /tmp/compute && grep -c '\"kind\": *\"iteration\"' /tmp/compute/compute.jsonl"
echo "iteration records: $(tail -n 1 "$work/step.log")" | tee -a "$summary"
[ "$keep" = 1 ] || rm -rf "$root/src" "$root/wheelhouse" "$root/stage"
echo "arm64-check: all steps passed; summary in $summary"
