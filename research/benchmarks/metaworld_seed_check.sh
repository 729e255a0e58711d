#!/usr/bin/env bash
# A training seed for an untouched check of the OOD scores (issue 32; research/results/metaworld_sweep_margin_full/
# summary.md): the light preset trained by the quickstart, the full perturbation sweep with E_c recorded, 100 fresh
# vanilla rollouts, and the records copied (gzipped) into the results folder's layout. Each stage skips what is on
# disk, so a killed run resumes. Write the check's rule into summary.md (and commit it) before running this.
#
#   bash research/benchmarks/metaworld_seed_check.sh 22000 23000     # about 30 min a seed on one core of a 2-core CPU
#
# A variant of the preset: VARIANT names its records' folder (seed<SEED>/<VARIANT>/, default the preset's
# "observation") and QUICKSTART_ARGS its overrides, e.g.
#   VARIANT=observation_appearance QUICKSTART_ARGS='--policy.joint_energy.corruptions=[channel_gain,state_noise]' \
#     bash research/benchmarks/metaworld_seed_check.sh 12000
#
# Then: research/benchmarks/score_summaries.py and research/benchmarks/window_typicality.py on seed<SEED>/observation/context_energy_*.
set -euo pipefail
cd "$(dirname "$0")/../.."
export MUJOCO_GL="${MUJOCO_GL:-egl}" OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
PY="${PY:-$PWD/.venv/bin/python}"
WORK="${WORK:-$PWD/outputs/seed_check}"
RESULTS="${RESULTS:-$PWD/research/results/metaworld_sweep_margin_full}"
VARIANT="${VARIANT:-observation}"
read -r -a QUICKSTART_OVERRIDES <<< "${QUICKSTART_ARGS:-}"

for SEED in "$@"; do
  run="$WORK/s$SEED${VARIANT#observation}"  # the preset in s<SEED>, a variant in s<SEED>_<rest of its name>
  checkpoint="$run/train/checkpoints/last/pretrained_model"
  mkdir -p "$WORK"
  if [ ! -d "$checkpoint" ]; then
    "$(dirname "$PY")/ebvla-quickstart" --output_dir="$run" --eval_episodes=1 --perturbation=none --vision_frames=1 \
      --seed="$SEED" "${QUICKSTART_OVERRIDES[@]}" > "$run.train.log" 2>&1
  fi
  (cd research/benchmarks && "$PY" metaworld_perturbation_sweep.py --checkpoint="$checkpoint" --output_dir="$run/sweep" \
    --tasks=button-press-v3 --episodes=8 --vanilla_episodes=40 --calibration_episodes=20 --observation_size=128 \
    --seed=3000 --calibration_seed=4000 --severities 3 5) > "$run.sweep.log" 2>&1
  if [ ! -f "$run/fresh/vanilla/energy_records.jsonl" ]; then
    "$PY" -c "from lerobot_policy_ebvla.pipelines.eval_energy import eval_metaworld_checkpoint
eval_metaworld_checkpoint('$checkpoint', '$run/fresh/vanilla', task='button-press-v3', device='cpu',
    max_episode_steps=150, n_episodes=100, seed=5000, perturbation='none', severity=0, observation_size=128)" \
      > "$run.fresh.log" 2>&1
  fi
  target="$RESULTS/seed$SEED/$VARIANT"
  for condition in "$run"/sweep/*/; do
    [ -f "$condition/energy_records.jsonl" ] || continue  # the sweep's ood_report folder
    mkdir -p "$target/context_energy_full/$(basename "$condition")"
    gzip -9 -n -c "$condition/energy_records.jsonl" \
      > "$target/context_energy_full/$(basename "$condition")/energy_records.jsonl.gz"
  done
  mkdir -p "$target/context_energy_fresh/vanilla"
  gzip -9 -n -c "$run/fresh/vanilla/energy_records.jsonl" > "$target/context_energy_fresh/vanilla/energy_records.jsonl.gz"
  echo "seed $SEED: records in $target ($(date -u))"
done
