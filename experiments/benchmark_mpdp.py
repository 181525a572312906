"""MPDP at scale: time and peak memory of ``predict`` by neighbour search.

  python -m experiments.benchmark_mpdp --sizes=10000,50000,200000 --k=8
  python -m experiments.benchmark_mpdp --sizes=200000 --methods=grid \\
      --shapes=donut --out=/tmp/mpdp_bench.json

For every (shape, size, method) a fresh subprocess builds the object, jits
``mpdp.make_predict(knn_method=method)`` with the shipped weights, measures
the compile time (``lower().compile()``) apart from the run (minimum wall
and process CPU time over ``--repeats`` runs, ``block_until_ready``), then
times the neighbour search alone as the network runs it, on the points'
integer lattice (``knn_s``; ``knn_float_s``: on the float points), and
reports its peak resident memory
(``ru_maxrss``, the whole process: Python, JAX and the data included) and,
on a GPU, the device allocator's peak (``device_peak_mib``; set
``XLA_PYTHON_CLIENT_PREALLOCATE=false`` so that it is what the case
needed) as one JSON line. ``brute`` (the O(N^2) search) is skipped where its
distance matrix alone would exceed ``--brute_max_gib``. A case whose
subprocess fails is a ``failed`` row, and the script exits 1 after the
other cases. Every row names the machine (``machine``: host, CPU model,
JAX's device kind).

Shapes (all valid points, scaled to about 0.1 m):
- ``torus``: uniform random points in a solid torus;
- ``donut``: the shipped real donut's Gaussian centres (45,624, a dense
  shell with sparse floaters), repeated with a small jitter up to N: the
  strongly varying density of a real capture;
- ``plate``: a thin plate (1 x 1 x 0.02), uniform random.
"""

from __future__ import annotations

import json
import os
import resource
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app
from absl import flags

from experiments.lib import cli
from physsplat_jax import mpdp
from physsplat_jax.errors import PhysSplatError
from physsplat_jax.mpdp import knn as knn_lib
from physsplat_jax.mpdp import model as model_lib

_SIZES = flags.DEFINE_list('sizes', ['10000', '50000', '200000'],
                           'Point counts N.')
_SHAPES = flags.DEFINE_list('shapes', ['torus', 'donut'],
                            'Objects: torus, donut, plate.')
_METHODS = flags.DEFINE_list('methods', ['grid', 'brute'],
                             'Neighbour searches: grid, brute.')
_K = flags.DEFINE_integer(
  'k', 8, 'Neighbours of the search-only timing (predict uses the '
  'shipped architecture, k = 8).')
_REPEATS = flags.DEFINE_integer('repeats', 2, 'Timed runs per case.',
                                lower_bound=1)
_BRUTE_MAX_GIB = flags.DEFINE_float(
  'brute_max_gib', 8.0, 'Skip brute where 4 N^2 bytes exceed this.')
_OUT = flags.DEFINE_string('out', None, 'Optional JSON results file.')
_CASE = flags.DEFINE_string('case', None,
                            'Internal: run one shape,size,method here.')


SHAPES = ('torus', 'donut', 'plate')
_KNOWN_METHODS = ('grid', 'brute')


class CaseError(PhysSplatError, RuntimeError):
  """A benchmark case's subprocess failed."""


def make_points(shape: str, n: int, seed: int = 0) -> np.ndarray:
  """(n, 3) float32 points of a benchmark object (see module docstring)."""
  rng = np.random.default_rng(seed)
  if shape == 'torus':
    R, r = 0.035, 0.015
    out = np.zeros((0, 3))
    while len(out) < n:
      p = rng.uniform(-1, 1, (2 * n, 3)) * [R + r, R + r, r]
      q = np.hypot(p[:, 0], p[:, 1]) - R
      out = np.concatenate([out, p[q * q + p[:, 2] ** 2 < r * r]])
    return out[:n].astype(np.float32)
  if shape == 'plate':
    return (rng.uniform(-0.5, 0.5, (n, 3)) * [0.1, 0.1, 0.002]).astype(
      np.float32)
  if shape == 'donut':
    from physsplat_jax.io import ply
    from physsplat_jax.scenes import donut
    x = np.asarray(ply.load_ply(donut.DONUT_PLY).means, np.float64)
    reps = -(-n // len(x))
    base = np.tile(x, (reps, 1))[:n]
    # Copies after the first are jittered by ~ a tenth of the median
    # spacing, so no two points coincide.
    jit = np.repeat(np.arange(reps) > 0, len(x))[:n, None]
    base = base + jit * rng.normal(0.0, 2e-4, base.shape)
    return (0.45 * base).astype(np.float32)
  raise app.UsageError(f'unknown shape {shape!r}; use torus, donut, plate')


def _timed(fn, args, repeats):
  t0 = time.perf_counter()
  compiled = fn.lower(*args).compile()
  compile_s = time.perf_counter() - t0
  walls, cpus = [], []
  for _ in range(repeats):
    t, c = time.perf_counter(), time.process_time()
    jax.block_until_ready(compiled(*args))
    walls.append(time.perf_counter() - t)
    cpus.append(time.process_time() - c)
  return compiled, compile_s, min(walls), min(cpus)


def _rss_mib() -> float:
  return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _device_peak_mib() -> float | None:
  """Peak bytes the device's allocator held (MiB), where it reports them
  (a GPU; the CPU client reports none)."""
  try:
    stats = jax.devices()[0].memory_stats()
  except Exception:  # noqa: BLE001 -- a backend without statistics
    return None
  if not stats or 'peak_bytes_in_use' not in stats:
    return None
  return round(stats['peak_bytes_in_use'] / 2**20, 1)


def run_case(shape: str, n: int, method: str, k: int, repeats: int) -> dict:
  """One measurement, in this process (see module docstring)."""
  pts = jnp.asarray(make_points(shape, n))
  mask = jnp.ones((n,), bool)
  params = mpdp.load_pretrained()
  means = mpdp.encode_means(2e5, 0.3, 800.0, 'fixed_corotated')
  rss0 = _rss_mib()
  predict = jax.jit(model_lib.make_predict(knn_method=method))
  _, compile_s, wall, cpu = _timed(predict, (params, pts, means, mask),
                                   repeats)
  res = dict(shape=shape, N=n, method=method, devices=str(jax.devices()),
             machine=cli.machine(),
             predict_compile_s=round(compile_s, 2),
             predict_s=round(wall, 3), predict_cpu_s=round(cpu, 3))
  knn = knn_lib.knn_grid if method == 'grid' else knn_lib.knn_brute
  # As the network searches: on the points' integer lattice (exact
  # distances); and on the float points, for the ratio.
  search = jax.jit(
    lambda p, m: knn(knn_lib.lattice_coordinates(p, m), m, k))
  compiled, compile_s, wall, cpu = _timed(search, (pts, mask), repeats)
  _, _, float_wall, _ = _timed(jax.jit(lambda p, m: knn(p, m, k)),
                               (pts, mask), repeats)
  res.update(knn_k=k, knn_compile_s=round(compile_s, 2),
             knn_s=round(wall, 3), knn_cpu_s=round(cpu, 3),
             knn_float_s=round(float_wall, 3))
  if method == 'grid':
    out = compiled(pts, mask)
    res.update(num_repaired=int(out.num_repaired),
               num_brute=int(out.num_brute))
  res.update(rss_before_mib=round(rss0), peak_rss_mib=round(_rss_mib()),
             device_peak_mib=_device_peak_mib())
  return res


def main(argv):
  del argv
  cli.positive_ints('k', [_K.value])
  if _CASE.value:
    shape, n, method = _CASE.value.split(',')
    print(json.dumps(run_case(shape, int(n), method, _K.value,
                              _REPEATS.value)), flush=True)
    return
  # All checked before the first case (a bad method or shape was found
  # after the cases before it had run, or only inside its subprocess).
  sizes = cli.positive_ints('sizes', _SIZES.value)
  for flag, given, known in (('methods', _METHODS.value, _KNOWN_METHODS),
                             ('shapes', _SHAPES.value, SHAPES)):
    bad = [v for v in given if v not in known]
    if bad or not given:
      raise cli.usage_error(f'--{flag}={",".join(given)}: unknown '
                            f'{bad or "(none given)"}; use {", ".join(known)}')
  cli.check_output_file('out', _OUT.value)  # (else lost after the cases)
  results = []
  for shape in _SHAPES.value:
    for n in sizes:
      for method in _METHODS.value:
        if method == 'brute' and 4.0 * n * n > _BRUTE_MAX_GIB.value * 2**30:
          res = dict(shape=shape, N=n, method=method,
                     skipped=f'distance matrix {4.0 * n * n / 2**30:.0f} GiB '
                     f'> --brute_max_gib={_BRUTE_MAX_GIB.value}')
        else:
          cmd = [sys.executable, '-m', 'experiments.benchmark_mpdp',
                 f'--case={shape},{n},{method}', f'--k={_K.value}',
                 f'--repeats={_REPEATS.value}']
          p = cli.run_child(cmd, env=dict(os.environ))
          lines = [ln for ln in p.stdout.splitlines() if ln.startswith('{')]
          if p.returncode == 0 and lines:
            res = json.loads(lines[-1])
          else:
            res = dict(shape=shape, N=n, method=method,
                       failed=f'exit {p.returncode}: '
                       f'{cli.last_error(p.stderr)}')
        print(json.dumps(res), flush=True)
        results.append(res)
  cli.write_json(_OUT.value, results)
  failed = [f'{r["shape"]},{r["N"]},{r["method"]}: {r["failed"]}'
            for r in results if 'failed' in r]
  if failed:
    # (exited 0.) The cases that worked are printed and in --out.
    raise CaseError(f'{len(failed)} case(s) failed: {"; ".join(failed)}')


if __name__ == '__main__':
  cli.run(main, cache_default='off')
