#!/usr/bin/env bash
# Issue 56 item 5: train the wider network of benchmarks/configs/gpu_wide.train_config.json (device auto: the
# GPU when torch sees one), then compare it with the shipped weights on hololens-dev (both frame sets, N = 5).
# Run from anywhere inside the repository; real-train must be at ../shared/data/real-train (the recipe's
# real.roots). Rerunning resumes the training from RUN/last.pt and keeps a finished model.pt.
#   tools/train_gpu.sh [RUN]        (RUN defaults to runs/gpu_wide)
set -euo pipefail
cd "$(dirname "$0")/.."
RUN=${1:-runs/gpu_wide}
PYTHON=${PYTHON:-python}
if [ ! -d ../shared/data/real-train ]; then
    echo "train_gpu.sh: $(pwd)/../shared/data/real-train is missing (the recipe's real.roots)" >&2
    exit 2
fi
"$PYTHON" -m colmap_pvs.cli train --config_file benchmarks/configs/gpu_wide.train_config.json \
    --output_dir "$RUN" --progress false
tail -n 3 "$RUN/log.csv"
for offset in 0 1; do
    "$PYTHON" benchmarks/hololens_quick.py --stride 3 --offset "$offset" --tag "gpu_wide_o$offset" \
        --checkpoint "$RUN/model.pt"
    "$PYTHON" benchmarks/hololens_quick.py --stride 3 --offset "$offset" --tag "shipped_o$offset"
done
