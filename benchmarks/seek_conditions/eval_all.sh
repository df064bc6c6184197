#!/usr/bin/env bash
# Every evaluation of a task's policy that docs/TRAINING.md reports, 100 episodes each:
# randomized (seeds 10000+), held out (seeds 20000+), the five robustness conditions, and the
# blind baselines on the randomized episodes (blank camera, constant forward; 50 each).
# The robustness conditions: a weak wheel either side, a dead-band, 66 ms of motor latency,
# a dark floor in dim light, and 150 ms motor plus 100 ms camera latency (a CSI pipeline on a
# Jetson Nano, issue 20).
# Writes OUT/<name>.json and prints one line: name=success ...
# SIM_LINES: [sim] lines added to every evaluation (e.g. SIM_LINES='lens = "pinhole"' for a
# policy trained through the pinhole).
# usage: [TASK=seek] [NUM_ENVS=2] [SIM_LINES=...] benchmarks/seek_conditions/eval_all.sh POLICY.onnx OUT_DIR [EPISODES]
set -eu
policy=$1; out=$2; episodes=${3:-100}; train=${JETBOT_TRAIN:-jetbot-train}
task=${TASK:-seek}; num_envs=${NUM_ENVS:-2}
here=$(dirname "$0")
mkdir -p "$out"
sim_lines=${SIM_LINES:-}
with_sim_lines() {  # a condition file (or none) with SIM_LINES in its [sim] table: a new file
  local file="$out/.config-$(basename "${1:-base.toml}")"
  if [ -n "${1:-}" ] && grep -q '^\[sim\]' "$1"; then
    awk -v add="$sim_lines" '{print} /^\[sim\]/{print add}' "$1" > "$file"
  else
    { printf '[sim]\n%s\n' "$sim_lines"; [ -n "${1:-}" ] && cat "$1"; true; } > "$file"
  fi
  echo "$file"
}
run() {  # name, then eval flags (a --config given last, if any)
  local name=$1; shift
  if [ -n "$sim_lines" ]; then
    local args=() config=""
    while [ $# -gt 0 ]; do
      if [ "$1" = --config ]; then config=$2; shift 2; else args+=("$1"); shift; fi
    done
    set -- "${args[@]}" --config "$(with_sim_lines "$config")"
  fi
  $train eval --task "$task" --policy "$policy" --episodes "$episodes" --num-envs "$num_envs" \
    --json --no-progress "$@" > "$out/$name.json"
  printf '%s=%s ' "$name" "$(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["success_rate"])' "$out/$name.json")"
}
run randomized --seed 10000
run heldout --seed 20000
for condition in weak_right_wheel weak_left_wheel deadband latency floor_light latency_250ms; do
  run "$condition" --config "$here/$condition.toml"
done
half=$(( (episodes + 1) / 2 ))
run blank --seed 10000 --ablate blank --episodes "$half"
run constant_forward --seed 10000 --ablate constant-forward --episodes "$half"
echo
