#!/bin/bash
# avoid, the bundled recipe on a calibrated robot (with_rugs_lift.toml), 16 envs, snapshots every
# 10 iterations; then randomized (calibrated and not) and held-out evaluations
source .devscripts/setup.sh
nproc; date; uptime
mkdir -p $OUT/la
timeout -s INT 445 jetbot-train train --task avoid --algo dagger --device cuda --num-envs 16 \
    --iterations 70 --steps-per-iteration 6000 --train-samples 48000 --final-learning-rate 1e-4 \
    --snapshots 10 --config benchmarks/training/with_rugs_lift.toml --no-progress \
    --out /tmp/la > /tmp/la.out 2> /tmp/la.err
echo "train rc $?"; tail -2 /tmp/la.out; tail -3 /tmp/la.err; date
cp /tmp/la/metrics.csv /tmp/la/*.onnx /tmp/la.out /tmp/la.err $OUT/la/ 2>/dev/null
p=/tmp/la/policy.onnx; [ -f $p ] || p=$(ls /tmp/la/policy_*.onnx | sort -V | tail -1)
echo "evaluating $p"
e() { n=$1; shift; timeout 40 jetbot-train eval --task avoid --policy $p --num-envs 16 --json --no-progress "$@" > $OUT/la/$n.json; python3 -c "import json; print('$n', json.load(open('$OUT/la/$n.json'))['success_rate'])"; }
e randomized --episodes 100 --seed 10000 --config benchmarks/training/lift.toml
e heldout --episodes 100 --seed 20000 --config benchmarks/training/lift.toml
e uncalibrated --episodes 100 --seed 10000
tar czf $OUT/la.tgz -C $OUT la && rm -rf $OUT/la; date
