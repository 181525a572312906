# Two commands do all set-up on a fresh machine (Python 3.11+ and pip only):
#   make demo   # simulate the built-in default scene and write a video
#   make test   # run the test suite
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
OUT ?= out/demo
SCENE ?= tabletop

.PHONY: demo test test-slow bench gpu-wheels venv clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

# Bytecode for the package (an editable install has none, and where
# PYTHONDONTWRITEBYTECODE is set each process would compile it from source:
# 0.12-0.15 s of every start on a 2-core VM); up to date in ~0.1 s.
BYTECODE := $(PY) -m compileall -q physsplat_jax experiments

demo: $(STAMP)
	@$(BYTECODE)
	$(PY) -m experiments.demo --scene=$(SCENE) --out=$(OUT)

# pytest exits 5 when it collects nothing: treat that as a failure too.
test: $(STAMP)
	JAX_PLATFORMS=cpu $(PY) -m pytest -n 2 --dist loadfile -q tests

test-slow: $(STAMP)
	JAX_PLATFORMS=cpu $(PY) -m pytest -q -m slow tests

# Speed figures (docs/benchmarks.md); minutes on a 2-core CPU.
bench: $(STAMP)
	@$(BYTECODE)
	$(PY) -m experiments.benchmark_mpm
	$(PY) -m experiments.benchmark_render
	$(PY) -m experiments.benchmark_pipeline --preset=cpu --out=out/bench_pipeline

# Wheels the lent GPU machine's image lacks (shared/GPU.md), for
# experiments/gpu_session.sh there (carry .whl): Python 3.12, x86-64.
# imageio-ffmpeg 0.6.0 (29 MB) rather than the newest (68 MB): the device
# tool carries 64 MiB per call, tree and wheels together.
GPU_WHEELS := trimesh==5.2.0 rtree==1.4.1 ml_collections==1.1.0 \
  PyYAML==6.0.4 gsplat==1.5.3 imageio-ffmpeg==0.6.0 flatbuffers==25.12.19
gpu-wheels:
	rm -rf .whl && mkdir -p .whl
	$(PYTHON) -m pip download --quiet --no-deps --only-binary=:all: \
	  --python-version 3.12 --implementation cp \
	  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
	  --platform manylinux2014_x86_64 -d .whl $(GPU_WHEELS)

clean:
	rm -rf $(VENV) out
