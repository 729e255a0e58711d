#!/usr/bin/env bash
# Sets the committed records aside before device calls, and puts them back after (run here, not on the machine).
#
# A device call carries the tracked tree with its parts, 64 MiB in all; the tree is over that with
# research/results (68 MiB on 2026-11-26, of which 62 MiB of records), which no GPU job reads. `aside` moves
# that folder into .results_aside/ (ignored, so it does not travel, and inside the checkout, so nothing is lost if
# the session ends first); `back` moves it home. Until then `git status` shows the records as deleted: commit
# nothing in between.
#
#   bash research/benchmarks/device_travel.sh aside     # then the device calls (research/benchmarks/libero_gpu_slices.sh)
#   bash research/benchmarks/device_travel.sh back
set -euo pipefail
cd "$(dirname "$0")/../.."
case "${1:-}" in
  aside)
    [ -e .results_aside ] && { echo ".results_aside exists: run 'back' first" >&2; exit 1; }
    mkdir .results_aside && mv research/results .results_aside/results
    echo "tracked tree now travels as $(git ls-files -z | xargs -0 stat -c %s 2>/dev/null \
      | awk '{s+=$1} END {printf "%.1f", s/2^20}') MiB" ;;
  back)
    [ -e research/results ] && { echo "research/results exists: nothing set aside to bring back" >&2; exit 1; }
    mv .results_aside/results research/results && rmdir .results_aside
    git status --short research/results | head -5 ;;
  *) echo "usage: $0 aside|back"; exit 2 ;;
esac
