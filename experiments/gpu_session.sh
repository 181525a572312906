#!/usr/bin/env bash
# Every GPU figure the open issues ask for, in one call on a lent GPU.
#
#   make gpu-wheels                        # here: the wheels the GPU image lacks
#   bash experiments/gpu_session.sh [BUDGET_S [STEP...]]   # there (carry .whl)
#
# Runs each step under `timeout`, all within BUDGET_S seconds (default
# 500, to fit one 10-minute device call with the install and the copy back;
# a step that would not fit is skipped, so the last ones may be). STEPs pick
# some of the steps below and run in the order given, most important first
# (default all, in the order below; `sweep` means all the sweeps), so the
# work can be split over two
# calls on a warm machine, e.g.
#   bash experiments/gpu_session.sh 430 env mpm_kernel pipeline substep \
#     substep_graphs
#   bash experiments/gpu_session.sh 430 video video_scene pipeline_scenes \
#     render donut mpm sweep
#   NO_GSPLAT=1 bash experiments/gpu_session.sh 540 env mpm_kernel \
#     substep_graphs pipeline video pipeline_scenes substep
# (on 2026-11-27 the H100 took 4 s for env, ~110 s for pipeline, 10 s for
# substep, 17 s per sweep and ~70 s for gsplat's build; the H200 in the
# NO_GSPLAT call above 5 s for env, 46 s for mpm_kernel, 52 s for
# substep_graphs, 143 s for pipeline (five runs), 13 s for video, 107 s
# for pipeline_scenes and 112 s for substep, 479 s in all; 15 minutes of
# device time in all, the machine's start (~30 s) included)
# A failing step's last lines are also printed, so they reach the call's
# output even when the tarball does not come back.
#   env       nvidia-smi, jax devices and versions
#   mpm_kernel  tests/mpm_pallas_test.py and mpm_graphs_test.py on the
#             GPU: the stress update's Pallas kernel compiled there against
#             the pure-JAX update; a frame launched as one CUDA graph, one
#             per substep and none, the same bits; and the 50k-particle
#             gradient of issue 17 (grad_finite_test's slow ScaleTest)
#   mpm       benchmark_mpm block at 10k / 100k / 1M (no naive reference)
#   mpm_visco  the same at 10k / 100k with the solids' Kelvin-Voigt
#             dashpot and with a Maxwell branch, against the plain block
#   mpdp      benchmark_mpdp: MPDP's field (grid neighbour search and the
#             shipped network) on 200k and 1M points, a torus and the
#             repeated donut: time, compile and the device's peak memory
#             (issue 17: a 1M-point object on the GPU)
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
#             per substep), each with the stress update as one Pallas
#             kernel (auto) and as XLA's fusion (jax)
#   substep_paper  benchmark_substep at the paper preset (64^3, up to 200k
#             particles: the donut's 58.9k, the tabletop's 10k) with a
#             profile: where a paper-scale substep's time goes
#   substep_graphs  the grouped and bare substeps with the frame launched
#             as one CUDA graph per substep (SimConfig.gpu_graphs=
#             'substep', XLA's default), one for the whole loop ('frame')
#             and none ('off'), one process
#   sorts     the optimised render program: are its sorts CUB radix sorts?
#   pipeline  benchmark_pipeline, paper preset (150 frames at 800x800, 768
#             substeps/frame), tabletop: cold, warm, warm unpipelined
#             (exact stage times), and a warm run traced over frames 60-64
#             (host wall and device-busy time per frame, costliest kernels),
#             and a warm run with the stress update as XLA's fusion
#             (constitutive_kernel=jax) (issue 17); PIPELINE_RUNS replaces
#             the list of runs (e.g. add warm@gpu_graphs=frame)
#   pipeline_scenes  the same preset on ficus and the donut (up to 200k
#             particles): cold and warm (issue 17's other scenes);
#             SCENES_RUNS replaces the list of runs (e.g. cold,warm,profile)
#   pipeline_noautotune  the cold run with XLA's GPU autotuning off
#   sweep_*   Pallas block and warps around the defaults (sweep_default),
#             1M at 1024^2
#   tests     the render, sorting and pipeline tests on the GPU
# gsplat (carried as a wheel) builds in the background (~80 s on 16 cores)
# when a step needs it; the steps that time the MLS-MPM or the pipeline
# (but `mpm`) wait for the build, so that it does not load the host
# under them. Everything lands in $OUT/gpu_session.tar.gz (the device tool
# returns at most 8 files) and a one-line-per-step $OUT/steps.txt.
set -u
BUDGET=${1:-500}
shift $(( $# > 0 ? 1 : 0 ))
# NO_GSPLAT=1: no gsplat build, and the render steps time ours alone.
NO_GSPLAT=${NO_GSPLAT:-}
GS=${NO_GSPLAT:+--nogsplat}
SWEEPS="sweep_default sweep_pallas_block16 sweep_pallas_block64 \
sweep_num_warps1 sweep_num_warps4"
ORDER="env mpm_kernel mpm mpm_visco mpdp render donut video video_scene substep \
substep_paper substep_graphs sorts pipeline pipeline_scenes pipeline_noautotune \
$SWEEPS tests"
STEPS=
for s in ${*:-all}; do
  case $s in
    all) STEPS="$STEPS $ORDER" ;;
    sweep) STEPS="$STEPS $SWEEPS" ;;
    *)
      if [[ " $ORDER " != *" $s "* ]]; then
        echo "gpu_session.sh: unknown step '$s'; steps: all $ORDER sweep" \
          >&2
        exit 2
      fi
      STEPS="$STEPS $s" ;;
  esac
done
START=$(date +%s)
OUT=${OUT:-out/gpu_session}
WORK=$(mktemp -d /tmp/gpu_session.XXXX)
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
# The same torch extension flags in every process as in gsplat's build
# below: with other flags, a step's first gsplat call rebuilds its CUDA
# code (~80 s; one possible reason, not verified, why the video step of
# 2026-11-27 ran past its limit before printing anything).
export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-16}
PY=${PYTHON:-python3}

if ls .whl/*.whl >/dev/null 2>&1; then
  $PY -m pip install -q --no-index --no-deps --no-cache-dir \
    --upgrade --target /tmp/site .whl/*.whl > "$WORK/install.log" 2>&1 \
    || echo "wheel install failed: see install.log" | tee -a "$OUT/steps.txt"
  export PYTHONPATH=/tmp/site:.
else
  export PYTHONPATH=.
fi
# Bytecode written once, here: where PYTHONDONTWRITEBYTECODE is set (this
# workplace's machines set it), every process otherwise compiles the
# package's 34k lines and the carried wheels' modules from source again
# (0.12-0.15 s of each start on the 2-core VM for the package alone).
$PY -m compileall -q -j 0 physsplat_jax experiments $( [ -d /tmp/site ] && echo /tmp/site ) \
  > "$WORK/compileall.log" 2>&1 || true

left() { echo $(( BUDGET - ($(date +%s) - START) )); }

# step NAME MAX_SECONDS COMMAND...: runs it under timeout (never past the
# budget) with its output in $WORK/NAME.log; one line in steps.txt.
step() {
  local name=$1 max=$2; shift 2
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

# gsplat compiles its CUDA code at first use: built in the background from
# the start when a step needs it (see the header).
GSPLAT=
for s in ${NO_GSPLAT:+none} $STEPS; do
  [[ $s == none ]] && break
  case $s in render|donut|video|video_scene)
    ( timeout 240 $PY -c \
      "from gsplat.cuda._backend import _C; print('gsplat built')" \
      > "$WORK/gsplat_build.log" 2>&1 ) &
    GSPLAT=$!
    break ;;
  esac
done
gsplat_wait() {
  if [[ -n $GSPLAT ]]; then wait "$GSPLAT" 2>/dev/null; GSPLAT=; fi
}

run_env() {
  step env 60 bash -c "nvidia-smi; $PY -c 'import jax, jaxlib; \
print(jax.__version__, jaxlib.__version__, jax.devices())'; \
$PY -m pip list 2>/dev/null | grep -i -E 'jax|flax|torch|gsplat|triton'"
}
run_mpm() {
  step mpm 90 $PY -m experiments.benchmark_mpm \
    --sizes=10000,100000,1000000 --naive=false --grad=false
}
# The solids' Kelvin-Voigt dashpot (its terms in the Pallas stress kernel)
# and the Maxwell branch (XLA's fusion beside it), each alternating with
# the plain block: never timed on a GPU (docs/benchmarks.md, round of
# 2026-11-29, third).
run_mpm_visco() {
  step mpm_visco 120 $PY -m experiments.benchmark_mpm \
    --sizes=10000,100000 --naive=false --grad=false --damped --maxwell \
    --out="$WORK/mpm_visco.json"
}
run_mpdp() {
  step mpdp 150 $PY -m experiments.benchmark_mpdp --sizes=200000,1000000 \
    --methods=grid --shapes=torus,donut --repeats=2 --out="$WORK/mpdp.json"
}
run_render() {
  gsplat_wait
  step render 200 $PY -m experiments.benchmark_render \
    --num=100000,1000000 --size=1024 --grad --backend=jax --pallas \
    --repeats=3 --out="$WORK/render.json" $GS
}
run_donut() {
  gsplat_wait
  step donut 90 $PY -m experiments.benchmark_render --scene=donut \
    --width=1024 --height=1024 --grad --backend=jax --pallas --repeats=5 \
    --out="$WORK/donut.json" $GS
}
# Issue 15's video target: 150 orbiting frames of 100k Gaussians at
# 800x800 through the pipeline's host path, and gsplat's same loop.
run_video() {
  gsplat_wait
  step video 150 $PY -m experiments.benchmark_render --num=100000 \
    --width=800 --height=800 --video_frames=150 --repeats=3 \
    --out="$WORK/video.json" $GS
}
# The same on the tabletop (16.7k Gaussians): the pipeline's render stage
# took 18 ms per frame there at this size.
run_video_scene() {
  gsplat_wait
  step video_scene 120 $PY -m experiments.benchmark_render \
    --scene=tabletop --width=800 --height=800 --video_frames=150 \
    --repeats=3 --out="$WORK/video_scene.json" $GS
}
run_substep() {
  gsplat_wait
  step substep 150 $PY -m experiments.benchmark_substep --scene=tabletop \
    --variants=scene,split,masked,no_plane_no_body,bare --profile \
    --constitutive_kernels=auto,jax --out="$WORK/substep.json"
}
run_substep_paper() {
  gsplat_wait
  step substep_paper 150 bash -c "for s in donut tabletop; do $PY -m \
experiments.benchmark_substep --preset=paper --scene=\$s \
--variants=scene,bare --profile --out=$WORK/substep_paper_\$s.json || exit; \
done"
}
# How the frame is launched (SimConfig.gpu_graphs), in one process: one
# CUDA graph per substep (XLA's default, ours), the substep loop as one
# graph (XLA's command buffers with WHILE) and no graphs.
run_substep_graphs() {
  gsplat_wait
  step substep_graphs 100 $PY -m experiments.benchmark_substep \
    --scene=tabletop --variants=scene,bare --gpu_graphs=substep,frame,off \
    --profile --out="$WORK/substep_graphs.json"
}
run_sorts() {
  step sorts 60 bash -c "XLA_FLAGS=--xla_dump_to=$WORK/hlo $PY -m \
experiments.benchmark_render --num=100000 --size=1024 --repeats=1 \
--nogsplat > /dev/null 2>&1; cd $WORK/hlo && \
grep -l DeviceRadixSort *after_optimizations.txt; \
grep -h -o 'custom_call_target=\"[^\"]*\"' *after_optimizations.txt \
| sort | uniq -c | grep -i sort; \
echo XLA sort ops: \$(cat *after_optimizations.txt | grep -c ' sort(')"
  rm -rf "$WORK/hlo"
}
# One process per run, one compile cache for the four: the later runs are
# warm. The frames, videos and trajectories (hundreds of MB) stay out of
# the tarball; the reports go in.
# PIPELINE_SET: extra --set overrides, e.g. render_config.backend=jax.
run_pipeline() {
  gsplat_wait
  step pipeline 320 $PY -m experiments.benchmark_pipeline --preset=paper \
    --scenes=tabletop \
    --runs=${PIPELINE_RUNS:-cold,warm,serial,profile,\
warm@constitutive_kernel=jax} \
    --profile_frames=60,64 \
    --out="$WORK/pipeline" --set="${PIPELINE_SET:-}"
}
run_pipeline_scenes() {
  gsplat_wait
  step pipeline_scenes 240 $PY -m experiments.benchmark_pipeline \
    --preset=paper --scenes=ficus,donut --runs=${SCENES_RUNS:-cold,warm} \
    --out="$WORK/pipeline_scenes" --set="${PIPELINE_SET:-}"
}
# The cold run again with XLA's GPU autotuning off: how much of the cold
# compile it is.
run_pipeline_noautotune() {
  gsplat_wait
  XLA_FLAGS="${XLA_FLAGS:-} --xla_gpu_autotune_level=0" \
  step pipeline_noautotune 120 $PY -m experiments.benchmark_pipeline \
    --preset=paper --scenes=tabletop --runs=cold \
    --out="$WORK/pipeline_noautotune" --set="${PIPELINE_SET:-}"
}
# Pallas launch settings at 1M, 1024^2, one process each; run
# sweep_default in the same call as the others to compare them.
run_sweep() {  # run_sweep NAME OPTION
  step "$1" 40 $PY -m experiments.benchmark_render --num=1000000 \
    --size=1024 --grad "$2" --repeats=5 --nogsplat --out="$WORK/$1.json"
}
run_sweep_default() { run_sweep sweep_default --repeats=5; }
run_sweep_pallas_block16() { run_sweep sweep_pallas_block16 --pallas_block=16; }
run_sweep_pallas_block64() { run_sweep sweep_pallas_block64 --pallas_block=64; }
run_sweep_num_warps1() { run_sweep sweep_num_warps1 --num_warps=1; }
run_sweep_num_warps4() { run_sweep sweep_num_warps4 --num_warps=4; }
# tests/conftest.py runs the tests on the CPU unless JAX_PLATFORMS says
# otherwise: name the GPU.
run_tests() {
  step tests 150 env JAX_PLATFORMS=cuda $PY -m pytest -q -n 8 \
    tests/render_pallas_test.py \
    tests/sorting_test.py tests/pipeline_test.py tests/render_test.py \
    tests/mpm_pallas_test.py tests/mpm_graphs_test.py
}
# The MPM stress kernel compiled for this GPU against the pure-JAX update
# (every model, float32/64, gradient, a whole frame): before timing it.
run_mpm_kernel() {
  step mpm_kernel 120 env JAX_PLATFORMS=cuda $PY -m pytest -q -n 4 \
    -m 'slow or not slow' \
    tests/mpm_pallas_test.py tests/mpm_graphs_test.py \
    tests/grad_finite_test.py::ScaleTest
}

for s in $STEPS; do
  "run_$s"
done

cp "$OUT/steps.txt" "$WORK/" 2>/dev/null
# Reports and logs only (the device tool returns files of 16 MiB at most).
(cd "$WORK" && find . -type f \( -name '*.json' -o -name '*.log' \
  -o -name '*.txt' \) -print0 | tar czf "$OUT/gpu_session.tar.gz" \
  --null -T -)
echo "done in $(( $(date +%s) - START )) s; $OUT/gpu_session.tar.gz"
