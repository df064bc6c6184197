#!/bin/sh
# The seam: the bundled seek.onnx (trained through the pinhole) evaluated through the fisheye,
# and the pinhole baseline on the same seeds. Run from the repository root:
#   sh benchmarks/results/lens_seam/run.sh
D=benchmarks/results/lens_seam
P=jetbot_rt/policies/seek.onnx
date -u +"start %Y-%m-%d %H:%M:%S UTC" > $D/when.txt
for seed in 10000 20000; do
  for lens in pinhole fisheye; do
    config=""
    [ $lens = fisheye ] && config="--config $D/fisheye.toml"
    start=$(date +%s)
    jetbot-train eval --task seek --policy $P --episodes 100 --seed $seed $config --json \
      --no-progress > $D/$lens-$seed.json
    echo "$lens seed $seed: $(( $(date +%s) - start )) s, load $(cut -d' ' -f1 /proc/loadavg)" >> $D/when.txt
  done
done
date -u +"end %Y-%m-%d %H:%M:%S UTC" >> $D/when.txt
