#!/bin/bash
# seek PPO from pixels, asymmetric critic, two arms at once (8 envs each, seed 1): a plain robot
# and a calibrated one (lift.toml); 420 s each, then 100 held-out episodes each, the lifted arm
# also uncalibrated and with a blank camera
source .devscripts/setup.sh
nproc; date; uptime
declare -A extra=( [plain]="" [lift]="--config benchmarks/training/lift.toml" )
for a in plain lift; do
  timeout -s INT 420 jetbot-train train --task seek --algo ppo --critic state --device cuda --num-envs 8 --seed 1 --total-timesteps 20000000 ${extra[$a]} --no-progress --out /tmp/arm_$a > /tmp/train_$a.out 2> /tmp/train_$a.err &
done
wait; date
mkdir -p $OUT/lp
for a in plain lift; do
  tail -2 /tmp/train_$a.out; tail -2 /tmp/train_$a.err
  cp /tmp/arm_$a/metrics.csv $OUT/lp/metrics_$a.csv; cp /tmp/arm_$a/policy.onnx $OUT/lp/policy_$a.onnx
done
e() { n=$1; p=$2; shift 2; timeout 40 jetbot-train eval --task seek --policy /tmp/arm_$p/policy.onnx --episodes 100 --seed 20000 --num-envs 16 --json --no-progress "$@" > $OUT/lp/eval_$n.json; python3 -c "import json; print('$n', json.load(open('$OUT/lp/eval_$n.json'))['success_rate'])"; }
e plain plain
e lift lift --config benchmarks/training/lift.toml
e lift_uncalibrated lift
e lift_blank lift --config benchmarks/training/lift.toml --ablate blank
tar czf $OUT/lp.tgz -C $OUT lp && rm -rf $OUT/lp; date
