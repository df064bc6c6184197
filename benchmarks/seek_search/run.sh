#!/usr/bin/env bash
# Recipe search for the seek policy (docs/TRAINING.md, "The recipe search"): trains every
# variant of a TSV file (name<TAB>jetbot-train flags) at once, 2 env workers and 1 torch
# thread each (the 2-core machine's setting), then evaluates each final policy on the 100
# randomized evaluation episodes and on the latency condition. Meant for a many-core machine
# (the device machine ran 8 variants on 16 cores in ~7 min).
# usage: benchmarks/seek_search/run.sh benchmarks/seek_search/v3.tsv OUT_DIR
set -u
variants=$1; out=$2; train=${JETBOT_TRAIN:-jetbot-train}
mkdir -p "$out"
while IFS=$'\t' read -r name flags; do
  [ -z "$name" ] && continue
  (
    # shellcheck disable=SC2086
    $train train --task seek --out "$out/$name" --num-envs 2 --torch-threads 1 --no-progress \
      $flags > "$out/$name.log" 2>&1
    for condition in randomized latency; do
      $train eval --task seek --policy "$out/$name/policy.onnx" --episodes 100 --num-envs 2 \
        --json --no-progress --config "benchmarks/seek_conditions/$condition.toml" \
        > "$out/${name}_$condition.json" 2>> "$out/$name.log"
    done
  ) &
done < "$variants"
wait
for f in "$out"/*_randomized.json; do
  name=$(basename "$f" _randomized.json)
  python3 -c "import json, sys; r = [json.load(open(p))['success_rate'] for p in sys.argv[2:]]; print(sys.argv[1], *r)" \
    "$name" "$f" "$out/${name}_latency.json"
done
