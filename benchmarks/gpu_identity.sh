#!/usr/bin/env bash
# One GPU call (docs/usage/gpus.md, "The identity prior at a larger size"), from the repository root:
#     OUT=out [SIZE=medium] [MINUTES=5] [BATCH=64] [VEHICLES=2000] [N=32] bash benchmarks/gpu_identity.sh [WHEELS]
set -u
OUT=${OUT:?OUT must name the output folder}
WORK=${WORK:-/tmp/identity}
T0=$(date +%s)
mkdir -p "$OUT" "$WORK"
source benchmarks/gpu_wheels.sh "${1:-.whl}" || exit 1
LOG=$OUT/session.log
stamp() { echo "$1 rc=$2 at $(( $(date +%s) - T0 )) s" | tee -a "$LOG"; }
python3 -c "
import json, os, torch
from pathlib import Path
from sar_zero123.config.json_io import config_to_dict
from sar_zero123.data.corpus_proxies import write_corpus_proxies
from sar_zero123.sim.corpus import write_prior_corpus
from sar_zero123.stages.prior import PriorConfig, prior_base_config
n, w = ${VEHICLES:-2000}, os.cpu_count()
write_corpus_proxies(write_prior_corpus('$WORK/corpus', num_vehicles=n, num_workers=w), num_vehicles=250,
                     candidates=2, oracle=True, num_workers=w)
prior = PriorConfig(output_dir='$WORK/prior', corpus='$WORK/corpus', num_vehicles=n, model_size='${SIZE:-medium}',
                    spatial_pose='proxy', input_tokens=True, proxy_oracle_prob=0.25, base_steps=10**6, seed=1,
                    train_batch_size=${BATCH:-64}, mixed_precision='bf16' if torch.cuda.is_available() else 'no',
                    vae='sar_zero123/pretrained/sim_prior_identity/vae')
base = config_to_dict(prior_base_config(prior, Path(prior.vae), Path(prior.corpus)))
Path('$WORK/unet.json').write_text(json.dumps({**base, 'max_train_minutes': ${MINUTES:-5}}))  # the clock stops it
" >>"$LOG" 2>&1
stamp corpus $?
accelerate launch --num_processes 1 train/finetune_pfm.py --config "$WORK/unet.json" >>"$LOG" 2>&1
stamp unet $?
python3 benchmarks/proxy_prior_views.py --pipeline sar-zero123/sim-prior-identity --compare "$WORK/prior/base/pipeline" \
    --pairs_per_class "${N:-32}" --out "$OUT/identity_${SIZE:-medium}.json" >>"$LOG" 2>&1
stamp benchmark $?
tar -C "$WORK/prior/base" -cf - pipeline | split -b 15m - "$OUT/pipeline.tar.part"
grep -v "it/s\]$" "$LOG" | tail -n 40
