#!/usr/bin/env bash
# One run of the seek recipe and every evaluation of its policy (docs/TRAINING.md, "Measured":
# the runs of issue 11's fourth session): trains into DIR/run, then
# benchmarks/seek_conditions/eval_all.sh into DIR/eval; DIR/summary.txt has the wall time,
# the load and one line of success rates. One at a time on the 2-core machine.
# usage: benchmarks/seek_search/trial.sh DIR SEED [jetbot-train flags...]
set -u
dir=$1; seed=$2; shift 2
train=${JETBOT_TRAIN:-jetbot-train}
mkdir -p "$dir"
start=$(date +%s)
$train train --task seek --out "$dir/run" --seed "$seed" --no-progress "$@" > "$dir/train.log" 2>&1
echo "train rc=$? $(( $(date +%s) - start )) s load $(cut -d' ' -f1-3 /proc/loadavg)" > "$dir/summary.txt"
"$(dirname "$0")/../seek_conditions/eval_all.sh" "$dir/run/policy.onnx" "$dir/eval" >> "$dir/summary.txt"
