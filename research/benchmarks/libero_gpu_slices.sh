#!/usr/bin/env bash
# The GPU jobs on a lent GPU machine (issues 21, 35), in device calls of at most 10 minutes.
#
# The machine has torch but no LeRobot, no LIBERO and no package index. `bash research/benchmarks/libero_gpu_bundle.sh`
# (run here first; research/tests/test_gpu_bundle.py proves such a bundle complete) leaves what it lacks in
# .gpu_bundle/part1 ... partN, each carried by one call (64 MiB per call with the working tree):
#   calls 1..N-1: bash research/benchmarks/libero_gpu_slices.sh unpack         carry [.gpu_bundle/partK]
#   call N:       bash research/benchmarks/libero_gpu_slices.sh start          carry [.gpu_bundle/partN]
#   then:         bash research/benchmarks/libero_gpu_slices.sh poll           (waits up to POLL_S, copies products to $OUT)
#   or, after start: bash research/benchmarks/libero_gpu_slices.sh vlm_bench   (the latency job, research/docs/vlm_gpu.md)
# Each call must follow the last within the 30 s the machine stays warm. `unpack` copies its part to the
# machine's disk; `start` copies the last, joins and checks the files (SHA-256), installs the wheels into a venv
# beside the machine's own packages with pip and no index (`research/benchmarks/gpu_bundle.py install`), unpacks the
# optional data and checkpoints into the work folder, extracts the EGL libraries, links LIBERO's assets, checks the
# imports and starts the driver. JOB=libero (the default) records, trains and evaluates. JOB=eval only evaluates
# the bundled checkpoints (`--checkpoint=RUN=DIR` at build time) or those carried in .gpu_bundle_checkpoints/<run>/,
# with frames rendered at IMAGE_SIZE (the recording's). JOB=none only installs. JOB=vlm installs a `gpu_bundle.py
# build --job=vlm` bundle (no LIBERO wheels), for vlm_bench in the same call. RUNS names the pipeline's runs,
# EVAL_ARGS the eval stage's queue (tasks, rollouts per job, conditions), EVAL_JOBS the evaluations side by side.
#
# The driver runs detached (its own session), so it lives across calls: record (skipped when the bundle brought
# the data), train until TRAIN_UNTIL_S after its start (or both runs done; a run with a bundled checkpoint
# resumes), evaluate until EVAL_UNTIL_S, packing its products after each stage and every minute of training into
# /tmp/libero_out (copied to $OUT by every call). STEPS is lerobot-train's --steps (its cosine schedule scales to
# it); a run stopped at TRAIN_UNTIL_S is evaluated at its last checkpoint. The minutes: research/docs/libero_runs.md.
set -uo pipefail
: "${BUNDLE:=/tmp/gpu_bundle}" "${VENV:=/tmp/venv}" "${WORK:=/tmp/libero_work}"
PRODUCTS=/tmp/libero_out
DRIVER=/tmp/libero_driver
PY=$VENV/bin/python
export MUJOCO_GL=egl LIBERO_CONFIG_PATH=$VENV/libero_config HF_HUB_OFFLINE=1 PYTHONUNBUFFERED=1
NVIDIA_EGL=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
[ -f "$NVIDIA_EGL" ] && export __EGL_VENDOR_LIBRARY_FILENAMES=$NVIDIA_EGL
: "${TRAIN_UNTIL_S:=900}" "${EVAL_UNTIL_S:=1380}" "${STEPS:=5000}" "${POLL_S:=560}" "${JOB:=libero}"
: "${RUNS:=ebvla_paper diffusion}" "${EVAL_ARGS:=--vanilla=20 --perturbed=5}" "${EVAL_JOBS:=14}" "${IMAGE_SIZE:=128}" "${DEVICE:=cuda}"

copy_part() {  # the carried part(s) of this call onto the machine's disk
  mkdir -p $BUNDLE
  for part in .gpu_bundle/part*/; do
    [ -f "$part/manifest.json" ] && cp -r "$part". $BUNDLE/ && echo "unpacked $part"
  done
  du -sh $BUNDLE
}

pack() {  # the archive of records and logs, and the light ebvla checkpoint in parts under 16 MiB
  mkdir -p "$PRODUCTS.tmp"
  $PY "$DRIVER/libero_pipeline.py" pack --work=$WORK --archive="$PRODUCTS.tmp/libero_results.tar.gz" >/dev/null
  ckpt=$WORK/train/ebvla_paper/checkpoints/last/pretrained_model
  if [ -f "$ckpt/model.safetensors" ]; then
    tar -C "$ckpt" -czhf - . | split -b 15M - "$PRODUCTS.tmp/ebvla_paper_ckpt.tgz.part"
  fi
  # What comes back from a call is at most 16 MiB a file.
  split -b 15M "$PRODUCTS.tmp/libero_results.tar.gz" "$PRODUCTS.tmp/libero_results.tar.gz.part"
  rm "$PRODUCTS.tmp/libero_results.tar.gz"
  rm -rf "$PRODUCTS" && mv "$PRODUCTS.tmp" "$PRODUCTS"
}

status() {
  echo "== $(date -u +%T) driver: $(tail -n 3 $WORK/driver.log 2>/dev/null | tr '\n' ' ')"
  for log in $WORK/logs/train_*.log; do
    [ -f "$log" ] && echo "$(basename "$log"): $(tail -c 300 "$log" | tr '\r' '\n' | grep -a . | tail -n 1)"
  done
  ls $WORK/data 2>/dev/null | wc -l | sed 's/^/recorded pieces: /'
  find $WORK/eval -name eval_info.json 2>/dev/null | wc -l | sed 's/^/eval jobs done: /'
  nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader 2>/dev/null
}

case "${1:-}" in
  unpack)
    copy_part
    nvidia-smi --query-gpu=name,driver_version --format=csv,noheader; nproc; python3 --version ;;
  start)
    copy_part
    python3 research/benchmarks/gpu_bundle.py install --bundle=$BUNDLE --venv=$VENV --work=$WORK || exit 1
    if [ "$JOB" = vlm ]; then  # a `--job=vlm` bundle: the latency job alone, no LIBERO
      $PY -c "import lerobot, lerobot_policy_ebvla; print('imports ok')"; exit $?
    fi
    for f in $BUNDLE/gl/*.deb; do [ -f "$f" ] && dpkg -x "$f" /; done; ldconfig
    $VENV/bin/ebvla-install-libero-assets || exit 1
    $PY -c "import lerobot, robosuite, libero, mujoco, av, lerobot_policy_ebvla; print('imports ok')" || exit 1
    [ "$JOB" = libero ] || [ "$JOB" = eval ] || exit 0
    mkdir -p $DRIVER $WORK && cp research/benchmarks/libero_pipeline.py research/benchmarks/libero_gpu_slices.sh $DRIVER/
    # A checkpoint carried beside the last part (.gpu_bundle_checkpoints/<run>/: its pretrained_model folder, in
    # `carry`) is evaluated as the run's last; the bundle need not be rebuilt for it.
    for ckpt in .gpu_bundle_checkpoints/*/; do
      [ -f "${ckpt}model.safetensors" ] || continue
      dest=$WORK/train/$(basename "$ckpt")/checkpoints/last/pretrained_model
      mkdir -p "$dest" && cp -r "$ckpt". "$dest"/ && echo "carried checkpoint: $dest"
    done
    # The eval stage renders at the recording's size, which it reads from the recording's summary.
    [ "$JOB" = eval ] && [ ! -f $WORK/recording_summary.json ] \
      && echo "{\"image_size\": $IMAGE_SIZE}" >$WORK/recording_summary.json
    setsid nohup bash $DRIVER/libero_gpu_slices.sh driver >>$WORK/driver.log 2>&1 < /dev/null &
    POLL_S=${START_POLL_S:-420} bash "$0" poll ;;
  driver)
    start=$(date +%s)
    cd $DRIVER
    if [ "$JOB" = libero ]; then
      # 20 recorders side by side on the 16 cores: one round instead of two (402 s for 16 + 4 on 2026-11-24).
      # Skipped when the bundle brought a recorded dataset (data/all).
      $PY libero_pipeline.py record --work=$WORK --episodes_per_task=20 --parts=2 --jobs=20 --image_size=128
      echo "recorded after $(($(date +%s) - start)) s"; pack
      # shellcheck disable=SC2086
      $PY libero_pipeline.py train --work=$WORK --runs $RUNS --steps=$STEPS --batch_size=32 \
          --workers=6 --device=$DEVICE --detach
      while [ $(($(date +%s) - start)) -lt "$TRAIN_UNTIL_S" ]; do
        all_done=1
        for run in $RUNS; do [ -f $WORK/train/$run/DONE ] || all_done=0; done
        [ $all_done = 1 ] && break
        sleep 60; pack
      done
      $PY libero_pipeline.py stop --work=$WORK; sleep 5
      echo "training stopped after $(($(date +%s) - start)) s"; pack
    fi
    # shellcheck disable=SC2086
    $PY libero_pipeline.py eval --work=$WORK --runs $RUNS --jobs=$EVAL_JOBS --device=$DEVICE $EVAL_ARGS \
        --deadline_s=$((EVAL_UNTIL_S - ($(date +%s) - start)))
    pack; echo "driver done after $(($(date +%s) - start)) s" ;;
  poll)
    for _ in $(seq 1 $((POLL_S / 20))); do
      grep -q "driver done\|Traceback" $WORK/driver.log 2>/dev/null && break
      sleep 20
    done
    status; cp $PRODUCTS/* "$OUT"/ 2>/dev/null; ls -la "$OUT" ;;
  vlm_bench)  # one slice of the latency job: the same call again resumes (--skip-existing); JSONs to $OUT
    out=/tmp/vlm_bench/${BENCH_NAME:-compile_modes}
    # shellcheck disable=SC2086
    timeout "${BENCH_TIMEOUT_S:-540}" $PY research/benchmarks/vlm_gpu_bench.py ${BENCH_ARGS:---train-head-steps 300 --batch-sizes 1 8 32 \
        --train-steps 6 --chunks 20 --profile --compile-modes off reduce-overhead default max-autotune} \
        --out-dir=$out --skip-existing --budget-s=${BUDGET_S:-420}
    $PY research/benchmarks/vlm_gpu_bench.py --table=/tmp/vlm_bench; tar -C /tmp/vlm_bench -czf "$OUT"/vlm_bench.tgz . ;;
  *) echo "usage: $0 unpack|start|poll|vlm_bench (driver: internal)"; exit 2 ;;
esac
