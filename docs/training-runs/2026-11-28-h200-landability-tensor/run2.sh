#!/bin/bash
# The second round of 2026-11-28 (same machine kind, same 300 s each, run.sh's settings): the
# wider network again with two more seeds, and widths 40 and 64, judged by the card's second rule.
set -u
S=${SECONDS_EACH:-300}
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD
common="--shared .pack/shared --device cuda --tensor-crops --threads 3 --seconds $S --batch 64 --crop 256"
python3 -m companion.training.landability $common --width 48 --seed 1 --out $OUT/t48-s1.onnx >$OUT/t48-s1.log 2>&1 &
python3 -m companion.training.landability $common --width 48 --seed 2 --out $OUT/t48-s2.onnx >$OUT/t48-s2.log 2>&1 &
python3 -m companion.training.landability $common --width 40 --seed 0 --out $OUT/t40-s0.onnx >$OUT/t40-s0.log 2>&1 &
python3 -m companion.training.landability $common --width 64 --seed 0 --out $OUT/t64-s0.onnx >$OUT/t64-s0.log 2>&1 &
wait
grep -h "trained\|(largest" $OUT/*.log
