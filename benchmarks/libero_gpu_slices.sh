#!/usr/bin/env bash
# benchmarks/libero_pipeline.py on a lent GPU machine, in calls of at most 10 minutes (issue 21).
#
# The machine has torch but no LeRobot, no LIBERO and no package index; `benchmarks/libero_gpu_bundle.sh`
# (run here first) puts what it lacks into three carried folders, too large for one call together (64 MiB):
#   call 1: bash benchmarks/libero_gpu_slices.sh unpack   carry [.gl, .carry]     (LIBERO-Object's assets, robosuite)
#   call 2: bash benchmarks/libero_gpu_slices.sh unpack   carry [.gl, .carry_av]  (PyAV: LeRobot's dataset writer
#           probes its video encoder even for PNG frames)
#   call 3: bash benchmarks/libero_gpu_slices.sh start    carry [.gl, .whl]       (wheels; starts the driver)
#   call 4+: bash benchmarks/libero_gpu_slices.sh poll    (waits up to POLL_S, copies the products to $OUT)
# Each call must follow the last within the 30 s the machine stays warm. The driver runs detached (its own
# session), so it lives across calls: record, train until TRAIN_UNTIL_S after its start (or both runs done),
# evaluate until EVAL_UNTIL_S, packing its products after each stage and every minute of training into
# /tmp/libero_out (copied to $OUT by every call). On 2026-11-24 the transfer calls and the start took about two
# minutes of device time and the recording almost seven: set TRAIN_UNTIL_S and EVAL_UNTIL_S (seconds from the
# driver's start) so that the last poll returns inside the session's device time. STEPS is lerobot-train's
# --steps (its cosine schedule scales to it); a run stopped at TRAIN_UNTIL_S is evaluated at its last checkpoint.
set -uo pipefail
SITE=/tmp/site
WORK=/tmp/libero_work
PRODUCTS=/tmp/libero_out
DRIVER=/tmp/libero_driver
export PYTHONPATH=$SITE PATH="$SITE/bin:$PATH" MUJOCO_GL=egl LIBERO_CONFIG_PATH=$SITE/libero_config
NVIDIA_EGL=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
[ -f "$NVIDIA_EGL" ] && export __EGL_VENDOR_LIBRARY_FILENAMES=$NVIDIA_EGL
: "${TRAIN_UNTIL_S:=900}" "${EVAL_UNTIL_S:=1440}" "${STEPS:=5000}" "${POLL_S:=560}"

gl_libraries() { for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; }

pack() {  # the archive of records and logs, and the light ebvla checkpoint in parts under 16 MiB
  mkdir -p "$PRODUCTS.tmp"
  python3 "$DRIVER/libero_pipeline.py" pack --work=$WORK --archive="$PRODUCTS.tmp/libero_results.tar.gz" >/dev/null
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
  unpack)  # whichever of the two large parts this call carries
    gl_libraries
    mkdir -p $SITE
    [ -f .carry/site.tar.xz ] && tar -C $SITE -xJf .carry/site.tar.xz
    ls .carry_av/*.whl >/dev/null 2>&1 && python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
        --upgrade --target $SITE .carry_av/*.whl
    du -sh $SITE
    nvidia-smi --query-gpu=name,driver_version --format=csv,noheader; nproc; python3 --version ;;
  start)
    gl_libraries
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target $SITE .whl/*.whl || exit 1
    ebvla-install-libero-assets || exit 1
    python3 -c "import lerobot, robosuite, libero, mujoco, lerobot_policy_ebvla; print('imports ok')" || exit 1
    mkdir -p $DRIVER $WORK && cp benchmarks/libero_pipeline.py benchmarks/libero_gpu_slices.sh $DRIVER/
    setsid nohup bash $DRIVER/libero_gpu_slices.sh driver >>$WORK/driver.log 2>&1 < /dev/null &
    POLL_S=420 bash "$0" poll ;;
  driver)
    start=$(date +%s)
    cd $DRIVER
    # 20 recorders side by side on the 16 cores: one round instead of two (402 s for 16 + 4 on 2026-11-24).
    python3 libero_pipeline.py record --work=$WORK --episodes_per_task=20 --parts=2 --jobs=20 --image_size=128
    echo "recorded after $(($(date +%s) - start)) s"; pack
    python3 libero_pipeline.py train --work=$WORK --runs ebvla_paper diffusion --steps=$STEPS --batch_size=32 \
        --workers=6 --device=cuda --detach
    while [ $(($(date +%s) - start)) -lt "$TRAIN_UNTIL_S" ]; do
      [ -f $WORK/train/ebvla_paper/DONE ] && [ -f $WORK/train/diffusion/DONE ] && break
      sleep 60; pack
    done
    python3 libero_pipeline.py stop --work=$WORK; sleep 5
    echo "training stopped after $(($(date +%s) - start)) s"; pack
    python3 libero_pipeline.py eval --work=$WORK --runs ebvla_paper diffusion --jobs=14 --device=cuda \
        --vanilla=20 --perturbed=5 --deadline_s=$((EVAL_UNTIL_S - ($(date +%s) - start)))
    pack; echo "driver done after $(($(date +%s) - start)) s" ;;
  poll)
    for _ in $(seq 1 $((POLL_S / 20))); do
      grep -q "driver done\|Traceback" $WORK/driver.log 2>/dev/null && break
      sleep 20
    done
    status; cp $PRODUCTS/* "$OUT"/ 2>/dev/null; ls -la "$OUT" ;;
  *) echo "usage: $0 unpack|start|poll (driver: internal)"; exit 2 ;;
esac
