#!/usr/bin/env bash
# Every evaluation of a task's policy that docs/TRAINING.md reports, 100 episodes each:
# randomized (seeds 10000+), held out (seeds 20000+), the five robustness conditions, and the
# blind baselines on the randomized episodes (blank camera, constant forward; 50 each).
# Writes OUT/<name>.json and prints one line: name=success ...
# usage: [TASK=seek] [NUM_ENVS=2] benchmarks/seek_conditions/eval_all.sh POLICY.onnx OUT_DIR [EPISODES]
set -eu
policy=$1; out=$2; episodes=${3:-100}; train=${JETBOT_TRAIN:-jetbot-train}
task=${TASK:-seek}; num_envs=${NUM_ENVS:-2}
here=$(dirname "$0")
mkdir -p "$out"
run() {  # name, then eval flags
  local name=$1; shift
  $train eval --task "$task" --policy "$policy" --episodes "$episodes" --num-envs "$num_envs" \
    --json --no-progress "$@" > "$out/$name.json"
  printf '%s=%s ' "$name" "$(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["success_rate"])' "$out/$name.json")"
}
run randomized --seed 10000
run heldout --seed 20000
for condition in weak_right_wheel weak_left_wheel deadband latency floor_light; do
  run "$condition" --config "$here/$condition.toml"
done
half=$(( (episodes + 1) / 2 ))
run blank --seed 10000 --ablate blank --episodes "$half"
run constant_forward --seed 10000 --ablate constant-forward --episodes "$half"
echo
