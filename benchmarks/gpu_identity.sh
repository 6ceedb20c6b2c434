#!/usr/bin/env bash
# One GPU call of at most ten minutes (docs/usage/gpus.md): `sim-prior-identity`'s recipe (input tokens, a
# quarter of the pairs given the vehicle itself as proxy) at a larger UNet, from scratch, then the eight named
# vehicles' benchmark against the bundled `sim-prior-identity` on the same pairs. From the repository root:
#
#     OUT=out [SIZE=medium] [MINUTES=5] [BATCH=64] [VEHICLES=2000] [N=32] bash benchmarks/gpu_identity.sh [WHEELS]
#
# The corpus and its proxies render on every CPU core; the UNet stage trains for MINUTES (bf16 where a GPU is
# there), then the benchmark (on the CPUs, N pairs per vehicle) writes OUT/identity_$SIZE.json. The pipeline
# comes back as OUT/pipeline.tar.part* (restore with `cat OUT/pipeline.tar.part* | tar x`).
set -u
OUT=${OUT:?OUT must name the output folder}
SIZE=${SIZE:-medium}
MINUTES=${MINUTES:-5}
BATCH=${BATCH:-64}
VEHICLES=${VEHICLES:-2000}
N=${N:-32}
WORK=${WORK:-/tmp/identity}
T0=$(date +%s)
mkdir -p "$OUT" "$WORK"
source benchmarks/gpu_wheels.sh "${1:-.whl}" || exit 1
LOG=$OUT/session.log
PRECISION=$(python3 -c "import torch; print('bf16' if torch.cuda.is_available() else 'no')")
stamp() { echo "$1 rc=$2 at $(( $(date +%s) - T0 )) s" | tee -a "$LOG"; }

python3 -c "
import os
from sar_zero123.sim.corpus import write_prior_corpus
from sar_zero123.data.corpus_proxies import write_corpus_proxies
workers = os.cpu_count()
corpus = write_prior_corpus('$WORK/corpus', num_vehicles=$VEHICLES, num_workers=workers)
write_corpus_proxies(corpus, num_vehicles=250, candidates=2, oracle=True, num_workers=workers)
" >>"$LOG" 2>&1
stamp corpus $?

# the prior stage's own UNet config (sar_zero123.stages.prior.prior_base_config), stopped by the clock
python3 -c "
import json
from pathlib import Path
from sar_zero123.config.json_io import config_to_dict
from sar_zero123.stages.prior import PriorConfig, prior_base_config
prior = PriorConfig(output_dir='$WORK/prior', corpus='$WORK/corpus', num_vehicles=$VEHICLES, model_size='$SIZE',
                    spatial_pose='proxy', input_tokens=True, proxy_oracle_prob=0.25, base_steps=1000000,
                    train_batch_size=$BATCH, mixed_precision='$PRECISION', seed=1,
                    vae='sar_zero123/pretrained/sim_prior_identity/vae')
base = prior_base_config(prior, Path(prior.vae), Path(prior.corpus))
Path('$WORK/unet.json').write_text(json.dumps({**config_to_dict(base), 'max_train_minutes': $MINUTES}))
" >>"$LOG" 2>&1
stamp config $?
accelerate launch --num_processes 1 --mixed_precision "$PRECISION" train/finetune_pfm.py \
    --config "$WORK/unet.json" >>"$LOG" 2>&1
stamp unet $?

python3 benchmarks/proxy_prior_views.py --pipeline sar-zero123/sim-prior-identity \
    --compare "$WORK/prior/base/pipeline" --pairs_per_class "$N" --out "$OUT/identity_$SIZE.json" >>"$LOG" 2>&1
stamp benchmark $?
tar -C "$WORK/prior/base" -cf - pipeline | split -b 15m - "$OUT/pipeline.tar.part"
grep -v "it/s\]$" "$LOG" | tail -n 40
