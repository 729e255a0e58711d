#!/usr/bin/env bash
# Success rate and energy of one checkpoint under every MetaWorld perturbation at graded severities
# (`--env.type=metaworld_ebvla`, docs/metaworld.md), written as one `ebvla-eval` folder per condition, then one
# held-out `ebvla-ood-report` over all of them. The vanilla rollouts of two seed ranges are evaluated too: the
# first calibrates, the second is the report's negatives.
#
#   CKPT=<pretrained_model folder> OUT=outputs/sweep TASKS=button-press-v3 bash benchmarks/metaworld_perturbation_sweep.sh
set -euo pipefail
export MUJOCO_GL="${MUJOCO_GL:-egl}"
CKPT="${CKPT:?set CKPT to a pretrained_model folder}"
OUT="${OUT:-outputs/metaworld_sweep}"
TASKS="${TASKS:-button-press-v3}"
EPISODES="${EPISODES:-5}"
MAX_STEPS="${MAX_STEPS:-150}"
SEVERITIES="${SEVERITIES:-3 5}"
PERTURBATIONS="${PERTURBATIONS:-pose fov light_dim light_bright light_color light_direction noise blur blank table_color table_texture distractor robot_init}"
BIN="${BIN:-$(dirname "$(command -v python)")}"

evaluate() {  # folder, seed, extra env options...
  local folder="$1" seed="$2"
  shift 2
  [ -f "$OUT/$folder/energy_records.jsonl" ] && return 0
  "$BIN/ebvla-eval" --policy.path="$CKPT" --env.type=metaworld_ebvla --env.task="$TASKS" --env.fast_render=true \
      --env.max_episode_steps="$MAX_STEPS" --eval.n_episodes="$EPISODES" --eval.batch_size=1 --seed="$seed" \
      --output_dir="$OUT/$folder" "$@" > "$OUT/$folder.log" 2>&1
}

mkdir -p "$OUT"
evaluate calibration 2000
evaluate vanilla 1000
for perturbation in $PERTURBATIONS; do
  for severity in $SEVERITIES; do
    evaluate "${perturbation}_s${severity}" 1000 --env.perturbation="$perturbation" \
        --env.perturbation_severity="$severity"
  done
done
ood=$(find "$OUT" -mindepth 1 -maxdepth 1 -type d -name '*_s[0-9]' | sort | paste -sd, -)
"$BIN/ebvla-ood-report" --calibration="[$OUT/calibration]" --vanilla="[$OUT/vanilla]" --ood="[$ood]" \
    --output_dir="$OUT/ood_report"
