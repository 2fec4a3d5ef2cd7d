#!/usr/bin/env bash
# Gather every wheel a companion needs into one directory, on a laptop with internet, for
# `deploy/install.sh --offline DIR` in a field without it.
#
#   deploy/wheelhouse.sh --platform aarch64|x86_64 --python 3.10|3.11|3.12 [--glibc X.Y] [--out DIR]
#                        [--standalone-python FILE]
# Options:
#   --platform ARCH            the companion's `uname -m` (Jetson: aarch64)
#   --python X.Y               the companion's Python (a standalone CPython is 3.11)
#   --glibc X.Y                the companion's glibc (`getconf GNU_LIBC_VERSION`; default 2.28): no wheel needs
#                              a newer one; below 2.28 there is no mpich wheel (JetPack 4: 2.27)
#   --out DIR                  where (default: wheelhouse-ARCH-pyXY)
#   --dry-run                  write requirements.txt and print the downloads it would make, download nothing
#   --standalone-python FILE   also carry a python-build-standalone "install_only" tarball for ARCH
#                              (cpython-3.11.*-ARCH-unknown-linux-gnu-install_only.tar.gz), for companions whose
#                              Python is older than 3.10 (JetPack 4)
# What it holds: NAC's own wheel, its dependencies and the mpich wheel as binary wheels for manylinux ARCH and
# that Python; mpi4py's source and its build tools too, for companions that compile mpi4py against the
# distribution's MPICH (glibc < 2.28); MANIFEST.txt (platform, Python, date) and SHA256SUMS.
set -euo pipefail

usage() { sed -n '2,20p' "$0" | sed 's/^# \{0,1\}//'; exit 2; }
die() { echo "wheelhouse.sh: $*" >&2; exit 2; }

here=$(cd "$(dirname "$0")" && pwd)
source_dir=$(dirname "$here")
platform="" py="" out="" standalone="" glibc=2.28 dry_run=0
while [ $# -gt 0 ]; do
    case "$1" in
        --platform) platform=$2; shift 2 ;;
        --python) py=$2; shift 2 ;;
        --out) out=${2%/}; shift 2 ;;
        --glibc) glibc=$2; shift 2 ;;
        --dry-run) dry_run=1; shift ;;
        --standalone-python) standalone=$2; shift 2 ;;
        -h|--help) usage ;;
        *) die "unknown option $1 (see --help)" ;;
    esac
done
case "$platform" in aarch64|x86_64) ;; *) die "--platform must be aarch64 or x86_64 (got '$platform')" ;; esac
[[ "$py" =~ ^3\.(1[0-9])$ ]] || die "--python must be 3.10 or newer, as X.Y (got '$py')"
[[ "$glibc" =~ ^2\.([0-9]+)$ ]] && [ "${BASH_REMATCH[1]}" -ge 17 ] || die "--glibc must be 2.17 or newer, as 2.N (got '$glibc')"
glibc_minor=${BASH_REMATCH[1]}
[ -z "$standalone" ] || [ -s "$standalone" ] || die "--standalone-python $standalone: no such file"
platforms=(--platform "manylinux2014_$platform")
for ((minor = glibc_minor; minor >= 17; minor--)); do platforms+=(--platform "manylinux_2_${minor}_$platform"); done
abi=cp${py/./}
out=${out:-wheelhouse-$platform-py${py/./}}
python=${PYTHON:-python3}
mkdir -p "$out"

mpich_wheel=no
[ "$glibc_minor" -ge 28 ] && mpich_wheel=yes
"$python" - "$source_dir/pyproject.toml" "$mpich_wheel" > "$out/requirements.txt" <<'PY'
import sys
try:
    import tomllib
except ImportError:
    import tomli as tomllib
project = tomllib.load(open(sys.argv[1], "rb"))["project"]
mpich = project["optional-dependencies"]["mpich"] if sys.argv[2] == "yes" else []
print("\n".join(project["dependencies"] + mpich))
PY
echo "==> binary wheels for $platform, CPython $py, glibc $glibc: $(tr '\n' ' ' < "$out/requirements.txt")"
if [ "$dry_run" = 1 ]; then
    echo "would run: pip download --only-binary :all: --implementation cp --python-version $py --abi $abi" \
        "--abi abi3 --abi none ${platforms[*]} --platform any -r requirements.txt pip setuptools wheel build;" \
        "then mpi4py's source (no-binary) and NAC's own wheel"
    exit 0
fi
"$python" -m pip download -q --disable-pip-version-check --dest "$out" --only-binary :all: \
    --implementation cp --python-version "$py" --abi "$abi" --abi abi3 --abi none \
    "${platforms[@]}" --platform any -r "$out/requirements.txt" pip setuptools wheel build
echo "==> mpi4py's source and build tools (for glibc < 2.28: compiled against the distribution's MPICH)"
mpi4py_version=$(ls "$out"/mpi4py-*.whl | head -n 1 | sed 's/.*mpi4py-\([^-]*\)-.*/\1/')
# --no-binary for mpi4py alone: with :all:, pip would build mpi4py's own build tools from source too, to read its
# metadata (minutes, where their wheels take seconds).
"$python" -m pip download -q --disable-pip-version-check --dest "$out" --no-deps --no-binary mpi4py \
    "mpi4py==$mpi4py_version"
echo "==> NAC's own wheel"
"$python" -m pip wheel -q --disable-pip-version-check --no-deps --wheel-dir "$out" "$source_dir"
if [ -n "$standalone" ]; then
    mkdir -p "$out/python"
    cp "$standalone" "$out/python/"
fi
{
    echo "platform: $platform"
    echo "python: $py"
    echo "glibc: $glibc"
    echo "made: $(date -u +%Y-%m-%dT%H:%M:%SZ) from $(cd "$source_dir" && git describe --always --dirty 2>/dev/null || echo 'a source tree')"
} > "$out/MANIFEST.txt"
(cd "$out" && find . -type f ! -name SHA256SUMS ! -name MANIFEST.txt | sort | xargs sha256sum > SHA256SUMS)
echo "==> $out: $(ls "$out"/*.whl | wc -l) wheels, $(du -sh "$out" | cut -f1); install with: deploy/install.sh --offline $out ..."
