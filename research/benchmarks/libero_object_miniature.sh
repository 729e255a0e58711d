#!/usr/bin/env bash
# The paper's LIBERO experiment in miniature (research/docs/libero_runs.md): train a light `ebvla` on scripted LIBERO-Object
# demonstrations, evaluate it in LeRobot's LIBERO env, then run LIBERO-Plus camera and lighting perturbations
# and report Table III on held-out rollouts. Every size is a variable, so the same script runs the 2-core CPU
# miniature (the defaults) and a larger run (for example STEPS=30000 EPISODES=10 TASKS=[0,1,...,9] on a GPU).
#
#   DATA=<folder of ebvla-record-libero's dataset> OUT=outputs/libero_mini bash research/benchmarks/libero_object_miniature.sh
set -euo pipefail
export MUJOCO_GL="${MUJOCO_GL:-egl}"
DATA="${DATA:?set DATA to the folder written by ebvla-record-libero}"
REPO_ID="${REPO_ID:-local/libero_object_expert}"
OUT="${OUT:-outputs/libero_mini}"
STEPS="${STEPS:-1500}"
BATCH="${BATCH:-16}"
DEVICE="${DEVICE:-cpu}"
TASKS="${TASKS:-[0,2,3,4,5,6]}"        # LIBERO-Object task ids evaluated
EPISODES="${EPISODES:-2}"              # vanilla episodes per task: the first half calibrates, the rest is held out
EPISODE_LENGTH="${EPISODE_LENGTH:-200}" # the scripted expert needs 139-185 steps
PERTURBATIONS="${PERTURBATIONS:-pose:5 light_dim:5}"
BIN="${BIN:-$(dirname "$(command -v python)")}"

CKPT="$OUT/train/checkpoints/last/pretrained_model"
if [ ! -d "$CKPT" ]; then
  # Two cameras and a learned token per task instruction: LIBERO-Object's tasks share a scene and differ by
  # the object named in the instruction, which the light backbone cannot read.
  "$BIN/lerobot-train" --policy.type=ebvla --policy.backbone=resnet --policy.dim_model=128 --policy.n_heads=4 \
      --policy.n_blocks=2 --policy.resnet.resize_shape=[96,96] --policy.resnet.vision_backbone_stages="${STAGES:-2}" \
      --policy.resnet.camera_tokens="${CAMERA_TOKENS:-keypoints}" '--policy.resnet.task_instructions=[]' \
      --policy.train_mcmc_steps_range=[2,4] --policy.optimizer_lr=5e-4 --policy.push_to_hub=false \
      --policy.device="$DEVICE" --dataset.repo_id="$REPO_ID" --dataset.root="$DATA" \
      --batch_size="$BATCH" --steps="$STEPS" --save_freq="$STEPS" --log_freq=100 --num_workers=0 \
      --wandb.enable=false --output_dir="$OUT/train"
fi

evaluate() {  # evaluate <name> <n_episodes> [extra ebvla-eval options]
  local name=$1 n=$2
  shift 2
  [ -f "$OUT/eval/$name/energy_records.jsonl" ] && return
  "$BIN/ebvla-eval" --policy.path="$CKPT" --policy.device="$DEVICE" --env.type=libero_ebvla \
      --env.task=libero_object --env.task_ids="$TASKS" --env.episode_length="$EPISODE_LENGTH" \
      --env.observation_height=128 --env.observation_width=128 --eval.n_episodes="$n" --eval.batch_size=1 \
      --normalized_energy_samples=32 --seed=1000 --output_dir="$OUT/eval/$name" "$@"
}

# LeRobot's LIBERO env starts episode i of a task from LIBERO's initial state i whatever the seed, so the
# vanilla run is split by episode: episodes [0, EPISODES/2) calibrate, the others are held out.
evaluate vanilla "$EPISODES"
"$BIN/python" - "$OUT/eval" "$EPISODES" <<'EOF'
import sys
from pathlib import Path

from lerobot_policy_ebvla.monitoring.records import read_energy_records, write_energy_records

folder, episodes = Path(sys.argv[1]), int(sys.argv[2])
records = read_energy_records(folder / "vanilla" / "energy_records.jsonl")
for name, keep in (("calib", lambda r: r.episode_index < episodes // 2), ("heldout", lambda r: r.episode_index >= episodes // 2)):
    write_energy_records(
        folder / f"vanilla_{name}" / "energy_records.jsonl", [r for r in records if keep(r)], overwrite=True
    )
EOF
# The perturbed runs start from the calibration's initial states, so only the camera or the light differs.
for condition in $PERTURBATIONS; do
  evaluate "${condition%%:*}${condition##*:}" $((EPISODES / 2)) \
      --env.perturbation="${condition%%:*}" --env.perturbation_severity="${condition##*:}"
done

"$BIN/ebvla-ood-report" --calibration="[$OUT/eval/vanilla_calib]" --vanilla="[$OUT/eval/vanilla_heldout]" \
    --ood="[$(for c in $PERTURBATIONS; do printf '%s,' "$OUT/eval/${c%%:*}${c##*:}"; done | sed 's/,$//')]" \
    --output_dir="$OUT/ood_report"

# Does the policy read its cameras at all? (research/docs/energy_study.md: check this before reading Table III.)
"$BIN/python" -c "
from lerobot_policy_ebvla.monitoring.vision import checkpoint_camera_dependence
print('Camera check on 16 dataset frames:', checkpoint_camera_dependence('$CKPT', '$DATA', '$REPO_ID', 16, 1000).summary())
" | tee "$OUT/camera_check.txt"
