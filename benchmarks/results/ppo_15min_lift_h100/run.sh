#!/bin/bash
# issue 21 target 3: seek PPO from pixels for 15 min in two segments (a call lasts <= 10 min),
# on a calibrated robot (benchmarks/training/lift.toml; the only change from
# ../ppo_15min_h100/run.sh):
# --critic state --target-kl 0.02 --augment 0.1, 16 envs, --overlap --balance, lr annealed to 0
# over 2.4 M steps (~15 min at ~2700 env steps/s). Segment 1: 500 s. Segment 2: --resume for at
# most 400 s (it ended by itself at 353 s), then 100 held-out episodes, the same blank,
# constant forward, 100 randomized, all calibrated, and the held-out ones not calibrated.
SEG=$1
source .devscripts/setup.sh
nproc; date -u; uptime; python3 -c "import torch; print(torch.__version__, torch.cuda.is_available())"
ARGS="--task seek --algo ppo --critic state --device cuda --num-envs 16 --seed 1 --timesteps 2400000 --target-kl 0.02 --augment 0.1 --overlap --balance --config benchmarks/training/lift.toml --no-progress --out /tmp/arm"
mkdir -p $OUT/r
if [ "$SEG" = 1 ]; then
  T=500; RES=""
else
  T=400; RES="--resume"
  if [ ! -f /tmp/arm/checkpoint.pt ]; then echo "cold machine: resuming from the carried checkpoint"; mkdir -p /tmp/arm; cp .devout/s8/checkpoint.pt .devout/s8/metrics.csv /tmp/arm/ || exit 1; fi
fi
t0=$(date +%s)
echo "jetbot-train train $ARGS $RES  (timeout -s INT $T)"
timeout -s INT $T jetbot-train train $ARGS $RES > /tmp/train$SEG.out 2> /tmp/train$SEG.err
echo "train rc $? wall $(( $(date +%s) - t0 )) s"; tail -3 /tmp/train$SEG.out; tail -25 /tmp/train$SEG.err
cp /tmp/arm/metrics.csv /tmp/arm/policy.onnx $OUT/r/
[ "$SEG" = 1 ] && cp /tmp/arm/checkpoint.pt $OUT/r/
cp /tmp/train$SEG.err $OUT/r/train$SEG.err
if [ "$SEG" = 2 ]; then
  e() { n=$1; shift; timeout 60 jetbot-train eval --task seek --policy /tmp/arm/policy.onnx --episodes 100 --num-envs 16 --json --no-progress "$@" > /tmp/ev/eval_$n.json; python3 -c "import json; d=json.load(open('/tmp/ev/eval_$n.json')); print('$n', d['success_rate'], d['wall_s'])"; }
  mkdir -p /tmp/ev
  L="--config benchmarks/training/lift.toml"
  e heldout --seed 20000 $L
  e blank --seed 20000 --ablate blank $L
  e constant --seed 20000 --ablate constant-forward $L
  e randomized --seed 10000 $L
  e heldout_uncalibrated --seed 20000
  tar -C /tmp -cf $OUT/r/evals.tar ev
fi
ls -la $OUT/r; date -u; echo "total $(( $(date +%s) - t0 )) s"
