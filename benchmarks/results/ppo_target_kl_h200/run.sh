#!/bin/bash
# seek PPO from pixels, asymmetric critic, two arms at once (8 envs each, seed 1): plain and
# --target-kl 0.02 (the KL per update grew to 0.05-0.1 in ppo_lift_h200); 420 s each, then 100
# held-out episodes each and the target-kl arm with a blank camera
source .devscripts/setup.sh
nproc; date; uptime
declare -A extra=( [plain]="" [kl]="--target-kl 0.02" )
for a in plain kl; do
  timeout -s INT 420 jetbot-train train --task seek --algo ppo --critic state --device cuda --num-envs 8 --seed 1 --total-timesteps 20000000 ${extra[$a]} --no-progress --out /tmp/arm_$a > /tmp/train_$a.out 2> /tmp/train_$a.err &
done
wait; date
mkdir -p $OUT/pk
for a in plain kl; do
  tail -2 /tmp/train_$a.out; tail -2 /tmp/train_$a.err
  cp /tmp/arm_$a/metrics.csv $OUT/pk/metrics_$a.csv; cp /tmp/arm_$a/policy.onnx $OUT/pk/policy_$a.onnx
done
e() { n=$1; p=$2; shift 2; timeout 40 jetbot-train eval --task seek --policy /tmp/arm_$p/policy.onnx --episodes 100 --seed 20000 --num-envs 16 --json --no-progress "$@" > $OUT/pk/eval_$n.json; python3 -c "import json; print('$n', json.load(open('$OUT/pk/eval_$n.json'))['success_rate'])"; }
e plain plain
e kl kl
e kl_blank kl --ablate blank
e plain_blank plain --ablate blank
ls -la $OUT/pk; date
