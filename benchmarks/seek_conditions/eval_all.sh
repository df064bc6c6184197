#!/usr/bin/env bash
# Every evaluation of a seek policy that docs/TRAINING.md reports, 100 episodes each:
# randomized (seeds 10000+), held out (seeds 20000+), the five robustness conditions.
# Writes OUT/<name>.json and prints one line: name=success ...
# usage: benchmarks/seek_conditions/eval_all.sh POLICY.onnx OUT_DIR [EPISODES]
set -eu
policy=$1; out=$2; episodes=${3:-100}; train=${JETBOT_TRAIN:-jetbot-train}
here=$(dirname "$0")
mkdir -p "$out"
run() {  # name, then eval flags
  local name=$1; shift
  $train eval --task seek --policy "$policy" --episodes "$episodes" --json --no-progress "$@" \
    > "$out/$name.json"
  printf '%s=%s ' "$name" "$(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["success_rate"])' "$out/$name.json")"
}
run randomized --seed 10000
run heldout --seed 20000
for condition in weak_right_wheel weak_left_wheel deadband latency floor_light; do
  run "$condition" --config "$here/$condition.toml"
done
echo
