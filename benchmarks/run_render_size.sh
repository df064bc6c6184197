#!/bin/sh
# The render-size figures (issue 10) in one command; run it on an otherwise idle machine.
#   sh benchmarks/run_render_size.sh            # 1 and 2 processes
#   PROCESSES="1 2 4 8 16" TAG=h100 sh benchmarks/run_render_size.sh
# Writes benchmarks/results/{sim,train,seam,camera_scale}[-TAG].{json,md}.
set -e
cd "$(dirname "$0")/.."
PY=${PYTHON:-python}
PROCESSES=${PROCESSES:-1 2}
echo "load before: $(cat /proc/loadavg)"
# shellcheck disable=SC2086
$PY benchmarks/bench_sim.py --processes $PROCESSES ${TAG:+--tag "$TAG"}
# shellcheck disable=SC2086
$PY benchmarks/bench_train.py --episodes 0 --throughput-steps 4096 --processes $PROCESSES \
    ${TAG:+--tag "$TAG"}
if [ -z "$TAG" ]; then
    $PY benchmarks/bench_seam.py
    $PY benchmarks/bench_camera_scale.py
fi
echo "load after: $(cat /proc/loadavg)"
