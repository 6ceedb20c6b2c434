#!/usr/bin/env bash
# One GPU call of at most ten minutes (docs/usage/gpus.md, "The prepared call"), from the repository root:
#
#     OUT=out LIMIT=540 [BATCH=256] [INIT=sar-zero123/sim-prior-rotated] [PROBE=1] [DECAY_STEPS=N] \
#         bash benchmarks/gpu_session.sh [WHEELS [EVALUATORS]]
#
# installs the missing wheels; with PROBE=1 times one step of the `micro` prior eager and compiled
# (step_operators.py); trains `rotated_input@micro` from INIT (none: from scratch) with gpu_prior.py in what
# is left of LIMIT, compiled unless the probe failed (once more uncompiled if that fails), the learning rate
# decaying to 0 at step DECAY_STEPS when given. Everything (timings, results.json, tar parts, log) in OUT.
set -u
OUT=${OUT:?OUT must name the output folder}
LIMIT=${LIMIT:-540}
BATCH=${BATCH:-256}
INIT=${INIT:-sar-zero123/sim-prior-rotated}
WHEELS=${1:-.whl}
EVALUATORS=${2:-.gpu/evaluators}
T0=$(date +%s)
left() { echo $((LIMIT - ($(date +%s) - T0))); }
minutes() { awk -v s="$1" 'BEGIN { printf "%.2f", (s > 0 ? s : 0) / 60 }'; }

mkdir -p "$OUT"
source benchmarks/gpu_wheels.sh "$WHEELS" || exit 1
LOG=$OUT/session.log  # one log: what comes back from the machine is at most eight files
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv >"$LOG" 2>&1

MODE=(--compile reduce-overhead)
if [ "${PROBE:-0}" = 1 ]; then
    timeout 45 python3 benchmarks/step_operators.py --batch_size "$BATCH" --bf16 --steps 10 --out "$OUT/ops.json" \
        >>"$LOG" 2>&1
    echo "eager probe rc=$? at $(( $(date +%s) - T0 )) s" | tee -a "$LOG"
    timeout 150 python3 benchmarks/step_operators.py --batch_size "$BATCH" --bf16 --steps 20 \
        --compile reduce-overhead --out "$OUT/ops_compiled.json" >>"$LOG" 2>&1 || MODE=()
    echo "compiled probe done at $(( $(date +%s) - T0 )) s: ${MODE[*]:-eager}" | tee -a "$LOG"
fi

ARM=rotated_input@micro
COMMON=(--evaluators "$EVALUATORS" --arms "$ARM" --train_batch_size "$BATCH" --init "$INIT" --num_vehicles 20000
    --corpus_minutes 0.4 --eval_reserve_minutes 0.8 --setup_minutes 0.8)
if [ -n "${DECAY_STEPS:-}" ]; then
    COMMON+=(--lr_scheduler cosine --max_train_steps "$DECAY_STEPS")
fi
python3 benchmarks/gpu_prior.py --out "$OUT" --work /tmp/work "${COMMON[@]}" "${MODE[@]}" \
    --budget_minutes "$(minutes $(($(left) - 20)))" >>"$LOG" 2>&1
echo "gpu_prior rc=$? at $(( $(date +%s) - T0 )) s" | tee -a "$LOG"
if [ ! -e "$OUT/rotated_input-micro.tar.part00" ] && [ "$(left)" -gt 200 ]; then
    mkdir -p "$OUT/eager"
    python3 benchmarks/gpu_prior.py --out "$OUT/eager" --work /tmp/work_eager "${COMMON[@]}" \
        --budget_minutes "$(minutes $(($(left) - 20)))" >>"$LOG" 2>&1
    echo "eager gpu_prior rc=$? at $(( $(date +%s) - T0 )) s" | tee -a "$LOG"
fi
grep -v "^USDT\|profiler_st" "$LOG" | tail -n 60
