#!/usr/bin/env bash
# Fills .whl/ (git-ignored) with the wheels experiments/gpu_job.sh installs on a leased GPU
# machine, whose image has JAX, flax, optax, orbax, scipy and absl but not mujoco:
# mujoco (cp312, stripped of what a headless MJX run never loads, so the tree that travels
# stays small: 26 MiB -> 8 MiB), mujoco-mjx (without its test data) and trimesh (mjx imports it).
#
#   bash experiments/gpu_wheels.sh        # then: run(..., carry=[".whl"])
set -euo pipefail
cd "$(dirname "$0")/.."
VERSION=$(python3 -c "import re; print(re.search(r'\"mujoco==([\d.]+)\"', open('pyproject.toml').read())[1])")
DEST=$(pwd)/.whl TMP=$(mktemp -d)
trap 'rm -rf "$TMP"' EXIT
grep -qx '/.whl/' .gitignore || { echo "/.whl/ must be in .gitignore" >&2; exit 1; }
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
  -d "$TMP/dl" "mujoco==$VERSION" "mujoco-mjx==$VERSION" trimesh

strip_wheel() {  # WHEEL PATHS...: rewrites WHEEL into $DEST without PATHS (and its RECORD without them)
  local whl=$1 dir="$TMP/unpacked"; shift
  rm -rf "$dir"; mkdir -p "$dir"; (cd "$dir" && python3 -m zipfile -e "$whl" .)
  (cd "$dir" && for pattern in "$@"; do rm -rf $pattern; done && find . -name "*.a" -delete)  # globs expand in $dir
  (cd "$dir" && python3 - "$DEST/$(basename "$whl")" <<'EOF'
import glob, os, sys, zipfile
record = glob.glob("*.dist-info/RECORD")[0]
keep = [line for line in open(record) if os.path.exists(line.split(",")[0])]
open(record, "w").writelines(keep)
with zipfile.ZipFile(sys.argv[1], "w", zipfile.ZIP_DEFLATED) as z:
    for root, _, files in os.walk("."):
        for f in sorted(files):
            z.write(os.path.join(root, f), os.path.relpath(os.path.join(root, f)))
EOF
  )
}

mkdir -p "$DEST"; rm -f "$DEST"/*.whl
strip_wheel "$(realpath "$TMP"/dl/mujoco-"$VERSION"-*.whl)" mujoco/experimental 'mujoco/_render_filament*' \
  'mujoco/_simulate*' mujoco/include mujoco/testdata 'mujoco/*_test.py'
strip_wheel "$(realpath "$TMP"/dl/mujoco_mjx-*.whl)" mujoco/mjx/test_data mujoco/mjx/integration_test
cp "$TMP"/dl/trimesh-*.whl "$DEST"/
ls -la "$DEST"
