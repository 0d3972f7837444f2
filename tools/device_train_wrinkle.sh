#!/bin/bash
# Lent-GPU run (session 10): continue the v6 wrinkle GRUs on the GPU, exact inside test split over
# CPU workers. RUNS="garment:k_collision ..."; MINUTES of training each; fit + wrinkle from
# build/gpu5/ckpt/<g>_{fit,wrinkle}.npz, or the last run's build/runs/<g>/<g>/wrinkle.pt if this machine has it.
# Prepare here: pack <g>_fit.npz and <g>_wrinkle.npz (tools/device_checkpoints.py pack --half) into
# build/gpu5/ckpt, with body.tar.xz (assets/body) and clips.tar.xz (training/sources/mocap/cmu-asfamc)
# beside them; carry build/gpu5, keep the travelling tree under 64 MiB (untrack assets/models,
# assets/body and training/sources for the call). Then, on the device:
#   RUNS="longsleeve:1e6 jacket:1e6 tshirt:3e5" MINUTES=7.0 LIMIT=565 bash tools/device_train_wrinkle.sh
set -u
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
nvidia-smi -L; python3 -c "import torch, numpy, scipy; print(torch.__version__, numpy.__version__, scipy.__version__, torch.cuda.is_available())"
[ -f assets/body/body.npz ] || tar -xJf build/gpu5/body.tar.xz -C assets || exit 1
[ -f training/sources/mocap/cmu-asfamc/02/02_02.amc ] || { mkdir -p training/sources/mocap/cmu-asfamc && tar -xJf build/gpu5/clips.tar.xz -C training/sources/mocap/cmu-asfamc; } || exit 1
python3 -c "
from inference.body import NEUTRAL_PHENOTYPES, BodyModel
from training.datasets import MotionBank, TRAIN_CLIPS, VALIDATION_CLIP
body = BodyModel.load(); neutral = body.shape(NEUTRAL_PHENOTYPES[None])
m = MotionBank.cached(TRAIN_CLIPS, body, neutral); v = MotionBank.cached((VALIDATION_CLIP,), body, neutral, 120)
print('motion banks', len(m.gamma), len(v.gamma))" || exit 1
mkdir -p $OUT/logs build/gpu5/init
for run in $RUNS; do
  IFS=: read g k <<< "$run"
  if [ -f build/runs/$g/$g/wrinkle.pt ]; then cp build/runs/$g/$g/wrinkle.pt build/gpu5/init/$g.pt; echo "$g: continuing this machine's last run";
  else python3 tools/device_checkpoints.py unpack build/gpu5/ckpt/${g}_fit.npz build/runs/$g/$g/fit.pt &&
       python3 tools/device_checkpoints.py unpack build/gpu5/ckpt/${g}_wrinkle.npz build/gpu5/init/$g.pt || exit 1; fi
  timeout $LIMIT python3 -m training.train_wrinkle --garment $g --device cuda --threads 1 --pose-workers 1 --inside-workers ${INSIDE_WORKERS:-3} --minutes $MINUTES \
    --init build/gpu5/init/$g.pt --out build/runs/$g --k-collision $k --exact-inside 1 --window 12 --lr ${LR:-1e-4} --lr-final 3e-5 > $OUT/logs/$g.log 2>&1 &
done
sleep 100; tail -n 2 $OUT/logs/*.log; nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv; uptime
wait
for run in $RUNS; do
  IFS=: read g k <<< "$run"
  [ -f build/runs/$g/$g/wrinkle.pt ] && python3 tools/device_checkpoints.py pack build/runs/$g/$g/wrinkle.pt $OUT/${g}_wrinkle.npz --half
  echo "== $g"; grep -E "validation|wrote|Error|step" $OUT/logs/$g.log | tail -n 5 | cut -c1-200
  python3 -c "
import json,sys; s=open('$OUT/logs/$g.log').read(); j=json.loads(s[s.index('metrics: ')+9:])
for k in ('validation_init','validation'): print(k, {q: round(j[k]['learned'][q],4) for q in ('static_j_per_frame','strain_j_per_frame','inside_fraction_exact')})" 2>/dev/null
done
tar -C $OUT -czf $OUT/logs.tgz logs && rm -rf $OUT/logs
ls -la $OUT
