#!/bin/bash
# The point-to-point evaluation's multi models (docs/point-to-point.md, "Multi models"):
# ground truth on twelve clouds, scene-a (the evaluated cloud, as thesis 6.5's multi
# model saw its evaluation cloud) and set-01 .. set-11, then the two networks, and the
# MLP once more without scene-a to measure generalization to an unseen cloud.
#
#   bench/p2p_multi.sh DATA OUT [NIMBUS]
#
# Every data set is seeded and resumable: rerun the script after a stop and it goes
# on where it stopped (same seed, same data, whatever the thread count). Sets a and
# b take about 294 s and 220 s on 16 cores, about 8x that on 2. The documented models
# were trained without set-05's set b: pass SKIP_B=set-05 to rebuild exactly them.
set -euo pipefail
data=${1:?data directory}
out=${2:?output directory}
nimbus=${3:-nimbus}
clouds="scene-a set-01 set-02 set-03 set-04 set-05 set-06 set-07 set-08 set-09 set-10 set-11"
seed() { case $1 in scene-a) echo $(($2 + 0)) ;; *) echo $(($2 + 10#${1#set-})) ;; esac; }
skip_b() { case " ${SKIP_B:-} " in *" $1 "*) return 0 ;; *) return 1 ;; esac; }
common="--resolution 128 --rho 25 --albedo 0.99 --g 0 --k 2 --chunk-size 10"
for c in $clouds; do
    # a: 600 points x 8 rotations, T to 20 % at 95 % (seeds 200 + N)
    "$nimbus" datagen p2p --cloud "$c" $common --points 600 --rotations 8 --max-rel-error 0.2 \
        --seed "$(seed "$c" 200)" --out "$data/p2p-multi2/a/$c" --quiet
    # b: 600 more points x 4 rotations (seeds 300 + N)
    skip_b "$c" && continue
    "$nimbus" datagen p2p --cloud "$c" $common --points 600 --rotations 4 --max-rel-error 0.2 \
        --seed "$(seed "$c" 300)" --out "$data/p2p-multi2/b/$c" --quiet
done
for c in $clouds; do
    [ "$c" = scene-a ] && continue
    # c: 100 points x 20 rotations, T to 10 % at 95 % (seeds 100 + N)
    "$nimbus" datagen p2p --cloud "$c" $common --points 100 --rotations 20 --max-rel-error 0.1 \
        --seed "$(seed "$c" 100)" --out "$data/p2p-multi/$c" --quiet
done
# The order of the sets decides the train/test split: the 100-point sets, then a, then b.
all=""
for c in $clouds; do [ "$c" = scene-a ] || all="$all $data/p2p-multi/$c"; done
for c in $clouds; do all="$all $data/p2p-multi2/a/$c"; done
for c in $clouds; do skip_b "$c" || all="$all $data/p2p-multi2/b/$c"; done
mkdir -p "$out"
# The multi models: the MLP of the shipped model's shape, and the thesis's residual network.
"$nimbus" train p2p $all --arch mlp --hidden 200,200 --epochs 40 --out "$out/multi"       # 53 s on 2 cores
"$nimbus" train p2p $all --epochs 20 --out "$out/multi_residual"                           # 299 s
# The same MLP without scene-a's data: how it does on a cloud it never saw.
"$nimbus" train p2p $(echo "$all" | tr ' ' '\n' | grep -v scene-a) --arch mlp --hidden 200,200 --epochs 40 \
    --out "$out/unseen"                                                                     # 48 s
