#!/usr/bin/env bash
# The drive / fine-tune proof of docs/DRIVE.md (issue 27), in the simulator: a hidden world the
# bundled seek policy fails in, the scripted person's recordings there (takeovers of the
# bundled policy, hand driving, then takeovers of the fine-tuned policy), the fine-tunes, and
# 100 held-out episodes each in that world and in the randomized simulator.
# Usage: benchmarks/drive/proof.sh WORK_DIR   (about an hour on 2 loaded cores; the drives run
# three at a time in real time, each with its own [sim] seed, i.e. its own scenes). The
# results in docs/DRIVE.md ran these steps by hand; some evaluations (blank, randomized) only
# for the policies the table shows them for.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
work=${1:?usage: proof.sh WORK_DIR}
mkdir -p "$work" && cd "$work"
seek=$(python -c 'from jetbot_rt.runtime.policy import bundled_policy_path as p; print(p("seek"))')
world() { sed "s/^task = \"seek\"/task = \"seek\"\nseed = $1/" "$here/hidden_world.toml" > "world_$1.toml"; }
drive() {  # seed duration record-dir [--policy P]
    world "$1"
    jetbot-rt drive --backend sim --input scripted --config "world_$1.toml" --duration "$2" \
        --record "$3" "${@:4}" > "$3.log" 2>&1
}
evaluate() {  # out policy [eval args]
    jetbot-train eval --task seek --episodes 100 --num-envs 2 --seed 10000 --json --no-progress \
        --policy "$2" "${@:3}" > "$1"
}

# round 1: takeovers of the bundled policy (3 x 200 s) and hand driving (3 x 110 s)
for s in 1 2 3; do drive "$s" 200 "takeover_$s" --policy "$seek" & done; wait
for s in 4 5 6; do drive "$s" 110 "hand_$s" & done; wait
ft() { out=$1; shift; jetbot-train finetune --init "$seek" --out "$out" --sim-share 0.5 "$@"; }
for d in 0 6; do  # --label-delay: the frame of the same tick, or of 0.2 s before
    ft "ft_takeover1_d$d" --recordings takeover_1 --holdout takeover_3 --label-delay $d
    ft "ft_all_d$d" --recordings takeover_1 takeover_2 takeover_3 --label-delay $d
    ft "ft_hand1_d$d" --recordings hand_4 --holdout takeover_3 --label-delay $d
    ft "ft_hand_d$d" --recordings hand_4 hand_5 hand_6 --holdout takeover_3 --label-delay $d
    ft "ft_mix_d$d" --recordings hand_4 hand_5 hand_6 takeover_1 --holdout takeover_3 \
        --label-delay $d
    ft "ft_mix_d${d}_seed1" --recordings hand_4 hand_5 hand_6 takeover_1 --holdout takeover_3 \
        --label-delay $d --seed 1
    ft "ft_mix10_d$d" --recordings hand_4 hand_5 hand_6 takeover_1 takeover_2 \
        --holdout takeover_3 --label-delay $d
done
ft ft_mix_d6_s07 --recordings hand_4 hand_5 hand_6 takeover_1 --holdout takeover_3 \
    --sim-share 0.7
# round 2 (HG-DAgger): takeovers of the delay-0 mix's policy, with the hand drives
for s in 7 8 9; do drive "$s" 90 "round2_$s" --policy ft_mix_d0/policy.onnx & done; wait
ft ft_round2 --recordings hand_4 hand_5 hand_6 round2_7 round2_8 round2_9 --holdout takeover_3 \
    --label-delay 0
ft ft_round2_sw1 --recordings hand_4 hand_5 hand_6 round2_7 round2_8 round2_9 \
    --holdout takeover_3 --label-delay 0 --stop-weight 1

for p in "$seek" ft_*/policy.onnx; do
    name=$(basename "$(dirname "$p")")
    evaluate "eval_${name}_hidden.json" "$p" --config "$here/hidden_world.toml"
    evaluate "eval_${name}_hidden_blank.json" "$p" --config "$here/hidden_world.toml" --ablate blank
    evaluate "eval_${name}_randomized.json" "$p"
done
