#!/bin/bash
# avoid on a calibrated robot with the wider network, seed 2 (the H200 run of 2026-11-29 lost
# its files); then randomized 400 and held out (calibrated), the weak right wheel and 150 + 100 ms
source .devscripts/setup.sh
nproc; date; uptime
mkdir -p $OUT/aw
timeout -s INT 420 jetbot-train train --task avoid --algo dagger --device cuda --num-envs 16 \
    --iterations 70 --steps-per-iteration 6000 --train-samples 48000 --final-learning-rate 1e-4 \
    --model-channels 32 64 64 --model-hidden 256 --seed 2 \
    --config benchmarks/training/with_rugs_lift.toml --no-progress \
    --out /tmp/aw > /tmp/aw.out 2> /tmp/aw.err
echo "train rc $?"; tail -2 /tmp/aw.out; tail -3 /tmp/aw.err; date; uptime
cp /tmp/aw/metrics.csv /tmp/aw/policy.onnx /tmp/aw.out /tmp/aw.err $OUT/aw/ 2>/dev/null
p=/tmp/aw/policy.onnx
h=benchmarks/seek_conditions
e() { n=$1; shift; timeout 100 jetbot-train eval --task avoid --policy $p --num-envs 16 --json --no-progress "$@" > $OUT/aw/$n.json; python3 -c "import json; print('$n', json.load(open('$OUT/aw/$n.json'))['success_rate'])"; }
e randomized_400 --episodes 400 --seed 10000 --config benchmarks/training/lift.toml
e heldout --episodes 100 --seed 20000 --config benchmarks/training/lift.toml
e weak_right_wheel --episodes 100 --config $h/weak_right_wheel.toml
e latency_250ms --episodes 100 --config $h/latency_250ms.toml
ls -la $OUT/aw; date
