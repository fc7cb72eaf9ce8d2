#!/usr/bin/env bash
# An ensemble at the 30-min budget (one seed): a geometry model and an image model each trained for
# about half the time of a REPORT.md row (cpu-few.yaml 21 epochs + cpu-image.yaml 4 epochs, ~28 min
# together on this 2-vCPU machine, one after the other), scored as one (`fusion evaluate --checkpoint
# A B`) on the 2,000 test frames of data/experiment-cpu30, whole and cut to the brightest N detections.
#   bash results/cpu30/equal_time_ensemble.sh          (env: SEED=1)
# Needs data/experiment-cpu30 (`fusion experiment --preset cpu30` renders it). The run folders go to
# results/cpu30/equal-time/ (their small files committed, checkpoints ignored).
set -euo pipefail
D=data/experiment-cpu30; R=results/cpu30/equal-time; S=${SEED:-1}
FUSION=${FUSION:-fusion}
$FUSION train --data $D --out $R/geometry_21ep-s$S --config configs/cpu-few.yaml \
    --set train.epochs=21 --set train.seed=$S --set train.progress=false
$FUSION train --data $D --out $R/image_4ep-s$S --config configs/cpu-image.yaml \
    --set train.epochs=4 --set train.seed=$S --set train.progress=false
for n in "" 3 4 5 6 10; do
  $FUSION evaluate --checkpoint $R/geometry_21ep-s$S $R/image_4ep-s$S --data $D --split test \
      --out $R/ensemble-s$S ${n:+--brightest $n}
done
