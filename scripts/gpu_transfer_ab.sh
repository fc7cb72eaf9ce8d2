#!/usr/bin/env bash
# What stream.image_transfer buys on a GPU (issue 24): the three-branch preset's frames batches
# crossing from the loader processes as float32 (stretched there) or as stored uint16 ADU (stretched
# on the device). One call on a GPU machine, everything on the same warm device:
#   bash scripts/gpu_transfer_ab.sh OUT_DIR
# env: WORKERS=15 EPOCHS=3 PY=python3; TRANSFERS="float adu" (the runs of step 4); AMP=auto (their
# train.amp; off: fp32); RUNS_ONLY=1 skips steps 2-3.
# 1. the cpu30 experiment's dataset (configs/experiments/cpu30.yaml: 2,500 frames);
# 2. the training loader alone, float then adu (benchmarks/loader_bench.py);
# 3. the training step alone as a run sets torch up (benchmarks/train_step_bench.py --deterministic,
#    mixed precision as the run has it (auto: bf16) and off);
# 4. the run of results/gpu/h200-2026-11-26-cpu-three for EPOCHS epochs, float then adu (metrics.csv:
#    epoch_time_s, validation included).
set -u
OUT=${1:?usage: gpu_transfer_ab.sh OUT_DIR}
W=${WORKERS:-15}; EPOCHS=${EPOCHS:-3}; PY=${PY:-python3}
TRANSFERS=${TRANSFERS:-float adu}; AMP=${AMP:-auto}; RUNS_ONLY=${RUNS_ONLY:-0}
DATA=${DATA:-/tmp/ab-data}
mkdir -p "$OUT"
log() { echo "== $(date +%T) $*"; }
log data
$PY -m skygen.cli render --n 2500 --set output.shard_size=500 --set "output.split_fractions=[0.05,0.15,0.8]" \
    --workers "$W" --out "$DATA" --force --quiet || exit 1
for t in float adu; do
  [ "$RUNS_ONLY" = 1 ] && break
  log "loader $t"
  $PY benchmarks/loader_bench.py --data "$DATA" --config configs/cpu-three.yaml --workers "$W" --batches 60 \
      --out "$OUT/loader-$t.json" stream.image_transfer=$t stream.render_backend=numpy train.threads=4
done
for amp in auto off; do
  [ "$RUNS_ONLY" = 1 ] && break
  log "step amp=$amp"
  $PY benchmarks/train_step_bench.py --config configs/cpu-three.yaml --batch-sizes 128 --amp $amp --deterministic \
      --out "$OUT/step-$amp.json"
done
for t in $TRANSFERS; do
  log "train $t amp=$AMP"
  $PY -m fusion.cli train --data "$DATA" --config configs/cpu-three.yaml --stream frames --force --out "/tmp/ab-$t-$AMP" \
      train.epochs="$EPOCHS" stream.render_backend=numpy train.workers="$W" train.device=cuda train.patience=null \
      train.progress=false stream.samples_per_epoch=73728 train.threads=4 stream.image_transfer=$t train.amp=$AMP \
    && cp "/tmp/ab-$t-$AMP/metrics.csv" "$OUT/metrics-$t-$AMP.csv"
  tail -n +2 "$OUT/metrics-$t-$AMP.csv" 2>/dev/null | cut -d, -f1,5,9
done
log done
