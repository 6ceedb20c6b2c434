#!/usr/bin/env bash
# One GPU call of at most ten minutes (docs/usage/gpus.md), from the repository root:
#
#     OUT=out LIMIT=555 [BATCH=256] [DATA=.gpu/mstar64] [PRESET=mstar-prior] bash benchmarks/gpu_mstar_session.sh [WHEELS]
#
# installs the missing wheels, then runs gpu_mstar_pfm.py on the crops in DATA: lambda = 0 and 4 at BATCH
# pairs per step in bf16 in what is left of LIMIT, two minutes kept for Table III. results.json, table3.md
# and one log in OUT.
set -u
OUT=${OUT:?OUT must name the output folder}
LIMIT=${LIMIT:-540}
BATCH=${BATCH:-256}
DATA=${DATA:-.gpu/mstar64}
PRESET=${PRESET:-mstar-prior}
T0=$(date +%s)
mkdir -p "$OUT"
source benchmarks/gpu_wheels.sh "${1:-.whl}" || exit 1
LOG=$OUT/session.log
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv >"$LOG" 2>&1
MINUTES=$(awk -v s="$((LIMIT - ($(date +%s) - T0) - 20))" 'BEGIN { printf "%.2f", (s > 0 ? s : 0) / 60 }')
python3 benchmarks/gpu_mstar_pfm.py run --data "$DATA" --out "$OUT" --work /tmp/work_mstar --recipe "$PRESET" \
    --budget_minutes "$MINUTES" --eval_reserve_minutes 2 --set "finetune_batch_size=$BATCH" mixed_precision=bf16 \
    >>"$LOG" 2>&1
echo "gpu_mstar_pfm rc=$? at $(( $(date +%s) - T0 )) s" | tee -a "$LOG"
tail -n 40 "$LOG"
