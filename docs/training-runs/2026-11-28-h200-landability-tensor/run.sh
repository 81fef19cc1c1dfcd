#!/bin/bash
# The landability runs of 2026-11-28 on a lent H200: crops made on the GPU (--tensor-crops), four
# runs side by side on the one GPU, each for the same seconds of training. Run from the repository
# root with the semantic-drone photos carried in .pack/shared (python -m companion.training.pack).
# OUT is where the models and logs go.
set -u
S=${SECONDS_EACH:-300}
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
python3 -c "import torch; print('torch', torch.__version__, torch.cuda.get_device_name())"
common="--shared .pack/shared --device cuda --tensor-crops --threads 3 --seconds $S --batch 64 --crop 256"
python3 -m companion.training.landability $common --width 32 --seed 0 --out $OUT/t32-s0.onnx >$OUT/t32-s0.log 2>&1 &
python3 -m companion.training.landability $common --width 32 --seed 1 --out $OUT/t32-s1.onnx >$OUT/t32-s1.log 2>&1 &
python3 -m companion.training.landability $common --width 32 --context 2 --seed 0 --out $OUT/t32c2-s0.onnx >$OUT/t32c2-s0.log 2>&1 &
python3 -m companion.training.landability $common --width 48 --seed 0 --out $OUT/t48-s0.onnx >$OUT/t48-s0.log 2>&1 &
sleep 60; nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader
wait
tail -n 4 $OUT/*.log
