#!/usr/bin/env bash
# Every GPU figure the open issues ask for, in one call on a lent GPU.
#
#   make gpu-wheels                        # here: the wheels the GPU image lacks
#   bash experiments/gpu_session.sh [BUDGET_S [STEP...]]   # there (carry .whl)
#
# Runs each step under `timeout`, all within BUDGET_S seconds (default
# 500, to fit one 10-minute device call with the install and the copy back;
# a step that would not fit is skipped, so the last ones may be). STEPs pick
# some of the steps below (default all; `sweep` means all the sweeps), so
# the work can be split over two calls on a warm machine, e.g.
#   bash experiments/gpu_session.sh 420 env mpm render donut video video_scene substep
#   bash experiments/gpu_session.sh 430 substep_graphs sorts pipeline tests sweep
# A failing step's last lines are also printed, so they reach the call's
# output even when the tarball does not come back.
#   env       nvidia-smi, jax devices and versions
#   mpm       benchmark_mpm block at 10k / 100k / 1M (no naive reference)
#   render    benchmark_render at 1024^2, 100k and 1M Gaussians on a sphere:
#             the JAX compositor, the compiled Pallas kernels (image PSNR
#             and gradient differences against JAX) and gsplat, forward and
#             gradient (issue 15's table)
#   donut     the same on the donut scene (issue 15)
#   video     a 150-frame 800x800 video of 100k Gaussians, rendered as
#             pipeline.run renders, and gsplat's same loop (issue 15)
#   video_scene  the same on the tabletop scene
#   substep   benchmark_substep on the tabletop: grouped (merged or split
#             constitutive slices) / masked / without body and plane / bare,
#             with a profile (device-busy time and the costliest kernels
#             per substep)
#   substep_graphs  the grouped and bare substeps again with XLA's command
#             buffers (CUDA graphs) off, and with loops as graphs too
#             (WHILE, CONDITIONAL), one process each
#   sorts     the optimised render program: are its sorts CUB radix sorts?
#   pipeline  benchmark_pipeline, paper preset (150 frames at 800x800, 768
#             substeps/frame), tabletop: cold, warm, warm unpipelined
#             (exact stage times), and a warm run traced over frames 50-100
#             (host wall and device-busy time per frame, costliest kernels)
#             (issue 17)
#   pipeline_noautotune  the cold run with XLA's GPU autotuning off
#   sweep_*   Pallas block and warps around the defaults (sweep_default),
#             1M at 1024^2
#   tests     the render, sorting and pipeline tests on the GPU
# gsplat (carried as a wheel) builds in the background during the MPM
# steps (~80 s on 16 cores). Everything lands in $OUT/gpu_session.tar.gz (the device tool
# returns at most 8 files) and a one-line-per-step $OUT/steps.txt.
set -u
BUDGET=${1:-500}
shift $(( $# > 0 ? 1 : 0 ))
STEPS=" ${*:-all} "
KNOWN="all env mpm render donut video video_scene substep substep_graphs \
sorts pipeline pipeline_noautotune sweep tests"
for s in $STEPS; do
  if [[ " $KNOWN " != *" $s "* ]]; then
    echo "gpu_session.sh: unknown step '$s'; steps: $KNOWN" >&2
    exit 2
  fi
done
START=$(date +%s)
OUT=${OUT:-out/gpu_session}
WORK=$(mktemp -d /tmp/gpu_session.XXXX)
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
PY=${PYTHON:-python3}

if ls .whl/*.whl >/dev/null 2>&1; then
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
    --upgrade --target /tmp/site .whl/*.whl > "$WORK/install.log" 2>&1 \
    || echo "wheel install failed: see install.log" | tee -a "$OUT/steps.txt"
  export PYTHONPATH=/tmp/site:.
else
  export PYTHONPATH=.
fi

left() { echo $(( BUDGET - ($(date +%s) - START) )); }
# wanted NAME: whether NAME (sweep_* as `sweep`) is among the chosen steps.
wanted() {
  [[ $STEPS == *" all "* || $STEPS == *" $1 "* \
     || ( $1 == sweep_* && $STEPS == *" sweep "* ) \
     || ( $1 == substep_graphs_* && $STEPS == *" substep_graphs "* ) ]]
}

# step NAME MAX_SECONDS COMMAND...: runs it under timeout (never past the
# budget) with its output in $WORK/NAME.log; one line in steps.txt.
step() {
  local name=$1 max=$2; shift 2
  wanted "$name" || return 0
  local t=$(left)
  if (( t < 20 )); then
    echo "$name skipped: budget spent" | tee -a "$OUT/steps.txt"
    return
  fi
  (( max > t - 10 )) && max=$(( t - 10 ))
  local t0=$(date +%s)
  timeout "$max" "$@" > "$WORK/$name.log" 2>&1
  local rc=$?
  echo "$name rc=$rc $(( $(date +%s) - t0 ))s (limit ${max}s)" \
    | tee -a "$OUT/steps.txt"
  if (( rc != 0 )); then tail -n 25 "$WORK/$name.log"; fi
}

step env 60 bash -c "nvidia-smi; $PY -c 'import jax, jaxlib; \
print(jax.__version__, jaxlib.__version__, jax.devices())'; \
$PY -m pip list 2>/dev/null | grep -i -E 'jax|flax|torch|gsplat|triton'"

# gsplat compiles its CUDA code at first use (~80 s on 16 cores): build it
# while the MPM steps use the GPU.
GSPLAT=
if wanted render || wanted donut || wanted video || wanted video_scene; then
  ( TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 timeout 240 $PY -c \
    "from gsplat.cuda._backend import _C; print('gsplat built')" \
    > "$WORK/gsplat_build.log" 2>&1 ) &
  GSPLAT=$!
fi

step mpm 90 $PY -m experiments.benchmark_mpm --sizes=10000,100000,1000000 \
  --naive=false --grad=false
[[ -n $GSPLAT ]] && wait $GSPLAT 2>/dev/null
step render 200 $PY -m experiments.benchmark_render \
  --num=100000,1000000 --size=1024 --grad --backend=jax --pallas \
  --repeats=3 --out="$WORK/render.json"
step donut 90 $PY -m experiments.benchmark_render --scene=donut \
  --width=1024 --height=1024 --grad --backend=jax --pallas --repeats=5 \
  --out="$WORK/donut.json"
# Issue 15's video target: 150 orbiting frames of 100k Gaussians at
# 800x800 through the pipeline's host path, and gsplat's same loop.
step video 90 $PY -m experiments.benchmark_render --num=100000 --width=800 \
  --height=800 --video_frames=150 --repeats=3 --out="$WORK/video.json"
# The same on the tabletop (16.7k Gaussians): the pipeline's render stage
# took 18 ms per frame there at this size.
step video_scene 90 $PY -m experiments.benchmark_render --scene=tabletop \
  --width=800 --height=800 --video_frames=150 --repeats=3 \
  --out="$WORK/video_scene.json"
# After the gsplat build: preparing its scene took 31 s beside it.
step substep 150 $PY -m experiments.benchmark_substep --scene=tabletop \
  --variants=scene,split,masked,no_plane_no_body,bare --profile \
  --out="$WORK/substep.json"
# Each substep is one CUDA graph by default (XLA's command buffers); the
# scan over substeps stays a host loop unless WHILE is enabled too.
XLA_FLAGS="${XLA_FLAGS:-} --xla_gpu_enable_command_buffer=" \
step substep_graphs_off 80 $PY -m experiments.benchmark_substep \
  --scene=tabletop --variants=scene,bare --profile \
  --out="$WORK/substep_graphs_off.json"
XLA_FLAGS="${XLA_FLAGS:-} --xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL" \
step substep_graphs_while 80 $PY -m experiments.benchmark_substep \
  --scene=tabletop --variants=scene,bare --profile \
  --out="$WORK/substep_graphs_while.json"
step sorts 60 bash -c "XLA_FLAGS=--xla_dump_to=$WORK/hlo $PY -m \
experiments.benchmark_render --num=100000 --size=1024 --repeats=1 \
--nogsplat > /dev/null 2>&1; cd $WORK/hlo && \
grep -l DeviceRadixSort *after_optimizations.txt; \
grep -h -o 'custom_call_target=\"[^\"]*\"' *after_optimizations.txt \
| sort | uniq -c | grep -i sort; \
echo XLA sort ops: \$(cat *after_optimizations.txt | grep -c ' sort(')"
rm -rf "$WORK/hlo"
# One process per run, one compile cache for the three: the serial run is
# warm too. The frames, videos and trajectories (hundreds of MB) are
# deleted below; the reports stay.
# PIPELINE_SET: extra --set overrides, e.g. render_config.backend=jax.
step pipeline 290 $PY -m experiments.benchmark_pipeline --preset=paper \
  --scenes=tabletop --runs=cold,warm,serial,profile --out="$WORK/pipeline" \
  --set="${PIPELINE_SET:-}"
# The cold run again with XLA's GPU autotuning off: how much of the cold
# compile it is.
XLA_FLAGS="${XLA_FLAGS:-} --xla_gpu_autotune_level=0" \
step pipeline_noautotune 120 $PY -m experiments.benchmark_pipeline \
  --preset=paper --scenes=tabletop --runs=cold \
  --out="$WORK/pipeline_noautotune" --set="${PIPELINE_SET:-}"
# The defaults first, so every setting is compared within one call.
for opt in --repeats=5 --pallas_block=16 --pallas_block=64 --num_warps=1 \
    --num_warps=4; do
  name=sweep_${opt#--}
  name=${name//=/}
  [[ $opt == --repeats=5 ]] && name=sweep_default
  step "$name" 40 $PY -m experiments.benchmark_render --num=1000000 \
    --size=1024 --grad "$opt" --repeats=5 --nogsplat \
    --out="$WORK/$name.json"
done
step tests 150 $PY -m pytest -q -n 8 tests/render_pallas_test.py \
  tests/sorting_test.py tests/pipeline_test.py tests/render_test.py

cp "$OUT/steps.txt" "$WORK/" 2>/dev/null
# Reports and logs only (the device tool returns files of 16 MiB at most).
(cd "$WORK" && find . -type f \( -name '*.json' -o -name '*.log' \
  -o -name '*.txt' \) -print0 | tar czf "$OUT/gpu_session.tar.gz" \
  --null -T -)
echo "done in $(( $(date +%s) - START )) s; $OUT/gpu_session.tar.gz"
