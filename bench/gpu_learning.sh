#!/usr/bin/env bash
# The GPU check: cvmeta trained with PPO on the GPU at a large batch, side by side with the
# same laptop recipe on one CPU thread, printing frames/s and val SR against minutes of training; then
# the `full` budget's Table 1 recipe (A3C, device cuda) for a few hundred episodes, unchanged but for
# its size. Never part of the tests. Run from the repository root on a machine with a GPU:
#
#     bash bench/gpu_learning.sh [MINUTES] [OUT_DIR] [SMOKE_DIR]
#
# DEVICE=cpu runs the same script on the CPU (how it is checked on a machine without a GPU).
set -euo pipefail
minutes=${1:-3}
out=${2:-reports/gpu_learning}
smoke=${3:-$out/full_smoke}
device=${DEVICE:-cuda}
workers=$(nproc)

python -m mapless scenes build train --workers "$workers"
python -m mapless scenes build val --workers "$workers"

# The small budget's cvmeta recipe (mapless/configs/budgets/small.yaml, per_model) with the imitation warm start.
recipe="model.target_context=true meta.first_order=true ppo.imitation_coef=1 ppo.imitation_frames=60000"
laptop="$recipe model.gcn_hidden=64 model.fusion_channels=8 ppo.minibatches=1"
python bench/learning_curve.py --parallel 3 --minutes "$minutes" --eval-every 1 --val-episodes 200 \
    --run "cvmeta device=$device ppo.envs=512 $laptop ppo.minibatches=4" \
    --run "cvmeta device=$device ppo.envs=512 ppo.minibatches=4 $recipe" \
    --run "cvmeta $laptop" \
    --out "$out"

# The full budget runs on the GPU unchanged (here cut to 640 training episodes and 5 test episodes per
# room type, one seed, cvmeta only).
python -m mapless reproduce table1 --budget full --set 'models=[cvmeta]' --set seeds=1 \
    --set train.episodes=640 --set train.checkpoint_every=320 --set train.device="$device" \
    --set eval.per_room=5 --set runs_dir="$smoke" --reports "$smoke"
