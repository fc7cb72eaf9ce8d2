#!/usr/bin/env bash
# Issue 38 item 2 on a lent GPU: is the few-star prior of configs/cpu-few-pair.yaml (pair features,
# magnitude noise up to 0.6 mag in training) short of samples or of capacity? Two runs side by side
# on one device, each with half the host cores as loader processes, both with 30 % flux-free samples
# (model.flux_dropout=0.3, as runs/few-pair-fd30 on the CPU):
#   small -- the preset's network (dim 64, 2 layers), only more samples than the CPU's 30 epochs;
#   large -- dim 128, 4 layers, 8 heads.
# A short probe of both (2 epochs of PROBE samples) sizes the epochs so that the runs end inside
# BUDGET seconds with their cosine schedule complete (not cut by a guard); SIGINT at 1.3 x BUDGET as
# a guard all the same (best.pt is written at every epoch's end). Validation: the frames of
# `skygen render --n 4000` (data/demo's recipe, the same content id), rendered on the device.
# The checkpoints come back and are scored on the CPU (benchmarks/prior_photometry.py, fusion
# benchmark), where the learned chain runs.
#   bash scripts/gpu_prior.sh OUT_DIR
# env: PY=python3 WORKERS=7 (per run) DEVICE=cuda BUDGET=390 PROBE=49152 DATA=/tmp/gp-data WORK=/tmp/gp
#      RUNS="small large" EXTRA="" (more overrides of every run)
# Back in OUT_DIR (at most 7 files): log.txt and per run NAME-metrics.csv, NAME-config.yaml, NAME-best.pt.
set -u
OUT=${1:?usage: gpu_prior.sh OUT_DIR}
PY=${PY:-python3}; W=${WORKERS:-7}; DEVICE=${DEVICE:-cuda}; BUDGET=${BUDGET:-390}; PROBE=${PROBE:-49152}
DATA=${DATA:-/tmp/gp-data}; WORK=${WORK:-/tmp/gp}; RUNS=${RUNS:-small large}; EXTRA=${EXTRA:-}
mkdir -p "$OUT" "$WORK"
exec > >(tee -a "$OUT/log.txt") 2>&1
log() { echo "== $(date +%T) $*"; }
log "env"; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null
$PY -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"
nproc
if [ ! -f "$DATA/manifest.json" ]; then
  log "data: skygen render --n 4000 (data/demo's recipe)"
  $PY -m skygen.cli render --n 4000 --workers $(( 2 * W )) --out "$DATA" --force --quiet || exit 1
fi
$PY -c "import json,sys; m=json.load(open(sys.argv[1])); print('dataset_id', m.get('dataset_id'), 'content_id', m.get('content_id'))" "$DATA/manifest.json"

overrides() {  # the run's own overrides
  case $1 in
    small) echo "" ;;
    large) echo "model.transformer.dim=128 model.transformer.layers=4 model.transformer.heads=8" ;;
    *) echo "unknown run $1" >&2; return 2 ;;
  esac
}
common="model.flux_dropout=0.3 train.workers=$W train.threads=1 train.device=$DEVICE train.amp=off train.progress=false $EXTRA"

train() {  # NAME OUTDIR GUARD_S more overrides...
  local name=$1 run=$2 guard=$3; shift 3
  timeout -s INT -k 30 "$guard" $PY -m fusion.cli train --data "$DATA" --config configs/cpu-few-pair.yaml --force \
      --out "$run" $common $(overrides "$name") "$@" > "$run.log" 2>&1
  echo "$name rc=$?" >> "$run.log"
}

log "probe: 2 epochs of $PROBE samples, runs side by side"
t0=$(date +%s)
pids=()
for name in $RUNS; do
  train "$name" "$WORK/probe-$name" 240 train.epochs=2 stream.samples_per_epoch="$PROBE" & pids+=($!)
done
wait "${pids[@]}"  # not a bare wait: that would also wait for the tee of the log
log "probe done in $(( $(date +%s) - t0 )) s"
declare -A EPOCHS
for name in $RUNS; do
  tail -3 "$WORK/probe-$name.log"
  cat "$WORK/probe-$name/metrics.csv" 2>/dev/null
  # seconds per sample from the second epoch (the first carries start-up); 98,304 samples an epoch as the preset
  EPOCHS[$name]=$($PY - "$WORK/probe-$name/metrics.csv" "$PROBE" "$BUDGET" <<'EOF'
import csv, sys
rows = list(csv.DictReader(open(sys.argv[1])))
per_sample = float(rows[-1]["epoch_time_s"]) / int(sys.argv[2])
print(max(2, int(float(sys.argv[3]) / (per_sample * 98304))))
EOF
)
  log "$name: ${EPOCHS[$name]} epochs of 98304 in about $BUDGET s"
done

guard=$(( BUDGET * 13 / 10 ))
log "train, runs side by side, SIGINT after $guard s"
t0=$(date +%s)
pids=()
for name in $RUNS; do
  train "$name" "$WORK/$name" "$guard" train.epochs="${EPOCHS[$name]}" & pids+=($!)
done
wait "${pids[@]}"
log "train done in $(( $(date +%s) - t0 )) s"
for name in $RUNS; do
  tail -5 "$WORK/$name.log"
  cp "$WORK/$name/metrics.csv" "$OUT/$name-metrics.csv" 2>/dev/null
  cp "$WORK/$name/config.yaml" "$OUT/$name-config.yaml" 2>/dev/null
  cp "$WORK/$name/best.pt" "$OUT/$name-best.pt" 2>/dev/null || log "$name: no best.pt"
done
ls -la "$OUT"
log done
