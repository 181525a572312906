"""MLS-MPM throughput benchmark (REFERENCE.md section 13 problem).

An elastic block (fixed corotated, E = 2e6 Pa, nu = 0.3, rho = 1000) of N
particles at 8 per cell on a 64^3 grid over the unit cube, dt = 4.34e-5 s,
gravity, a sticky floor, thrown at the floor at 2 m/s from one cell above
it (reached after ~180 substeps, after the timed runs), float32. For each N:
compile time, the median over 3 runs of 100 substeps after a warm-up, in
particle-substeps per second, XLA's memory estimate, and the same for a
naive reference (array-of-structures, ``jnp.linalg.svd`` polar, ``einsum``
3x3 algebra, ``.at[].add`` scatter), timed in the same process so that the
ratio survives a shared machine. Optionally the cost of a gradient
(d centre-of-mass / dE, N = 10k, 100 substeps) relative to the forward,
and (``--damped``) of a Kelvin-Voigt viscosity (``solid_viscosity``, 1 Pa
s) or (``--maxwell``) of a Maxwell branch (``SimConfig.maxwell``, E_N = E,
1 Pa s) against the same block without, alternating.

python -m experiments.benchmark_mpm [--sizes=10000,50000,200000] [--grad]
  [--naive] [--damped] [--maxwell] [--out=bench.json]
"""

import itertools
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import flags

from experiments.lib import cli
from physsplat_jax import mpm

_SIZES = flags.DEFINE_list('sizes', ['10000', '50000', '200000'],
                           'particle counts')
_STEPS = flags.DEFINE_integer('steps', 100, 'substeps per timed run',
                              lower_bound=1)
_REPEATS = flags.DEFINE_integer('repeats', 3, 'timed runs (median)',
                                lower_bound=1)
_NAIVE = flags.DEFINE_bool('naive', True, 'also time the naive reference')
_DAMPED = flags.DEFINE_bool(
  'damped', False, 'also time the block with a Kelvin-Voigt viscosity '
  '(SimConfig.solid_viscosity), alternating with the plain block')
_MAXWELL = flags.DEFINE_bool(
  'maxwell', False, 'also time the block with a Maxwell branch '
  '(SimConfig.maxwell), alternating with the plain block')
_GRAD = flags.DEFINE_bool('grad', True, 'time a gradient at the first size')
_OUT = cli.define_out(None, 'optional JSON output')

GRID = mpm.GridSpec(res=64, size=1.0)
E, NU, RHO, DT = 2e6, 0.3, 1000.0, 4.34e-5
FLOOR = 0.1


def make_block(n: int) -> np.ndarray:
  """n particles on a lattice of spacing dx/2 (8 per cell), near-cubic.

  Centred in x and y, its bottom one cell above the sticky floor. (At 2
  m/s it reaches the floor after about 180 substeps: the timed runs, 100
  substeps each from the initial state, time a falling block; every
  particle's stress is computed either way.)
  """
  k = int(np.ceil(n ** (1 / 3)))
  i = np.stack(np.meshgrid(*[np.arange(k)] * 3, indexing='ij'), -1)
  i = i.reshape(-1, 3)[:n]
  sp = GRID.dx / 2
  corner = np.array([0.5 - 0.5 * k * sp, 0.5 - 0.5 * k * sp,
                     FLOOR + GRID.dx])
  return corner + (i + 0.5) * sp


def make_config(steps: int) -> mpm.SimConfig:
  return mpm.SimConfig(
    grid=GRID, dt=DT, substeps_per_frame=steps, gravity=(0.0, 0.0, -9.8),
    boundary_conditions=(mpm.SurfaceCollider(point=(0.0, 0.0, FLOOR)),),
    remat_frames=False)


def _median_time(fn, args, repeats):
  """Median wall time and median process CPU time (all threads) [s]."""
  out = fn(*args)
  jax.block_until_ready(out)
  ts, cs = [], []
  for _ in range(repeats):
    c0 = time.process_time()
    t0 = time.perf_counter()
    out = fn(*args)
    jax.block_until_ready(out)
    ts.append(time.perf_counter() - t0)
    cs.append(time.process_time() - c0)
  return float(np.median(ts)), float(np.median(cs))


def _memory(compiled):
  try:
    m = compiled.memory_analysis()
    return int(m.temp_size_in_bytes + m.argument_size_in_bytes
               + m.output_size_in_bytes)
  except Exception:  # noqa: BLE001 (not all backends report it)
    return -1


def bench_package(n, steps, repeats, viscosity=0.0, maxwell=False):
  cfg = make_config(steps).replace(solid_viscosity=viscosity > 0,
                                   maxwell=maxwell)
  x = make_block(n)
  extra = dict(maxwell_E=E, maxwell_nu=NU, maxwell_viscosity=1.0) if (
    maxwell) else {}
  mat = mpm.make_materials('fixed_corotated', E, NU, RHO, num=n,
                           viscosity=viscosity, **extra)
  s = mpm.init_state(x, (0.0, 0.0, -2.0), (GRID.dx / 2) ** 3, mat, cfg)
  t0 = time.perf_counter()
  c = jax.jit(mpm.make_frame(cfg)).lower(s, mat, None).compile()
  compile_s = time.perf_counter() - t0
  sec, cpu = _median_time(lambda s_: c(s_, mat, None), (s,), repeats)
  out = c(s, mat, None)
  return dict(variant='physsplat_jax' + ('+kv' if viscosity else '')
              + ('+maxwell' if maxwell else ''),
              n=n, compile_s=compile_s,
              substep_ms=1e3 * sec / steps, mpss=n * steps / sec / 1e6,
              cpu_mpss=n * steps / cpu / 1e6, memory_mb=_memory(c) / 2 ** 20,
              com=np.asarray(out.x).mean(0).tolist())


# ------------------------------------------------------- naive reference

_OFF = np.array(list(itertools.product(range(3), repeat=3)))


def naive_substep(state, mat, dt):
  """Straightforward AoS MLS-MPM substep (the reference's naive variant)."""
  x, v, C, F = state
  mu, lam, mass, vol = mat
  G, inv_dx, dx = GRID.res, GRID.inv_dx, GRID.dx
  base = jnp.floor(x * inv_dx - 0.5).astype(jnp.int32)
  fx = x * inv_dx - base
  w = jnp.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2,
                 0.5 * (fx - 0.5) ** 2])
  U, sig, Vt = jnp.linalg.svd(F)
  R = U @ Vt
  J = jnp.prod(sig, -1)
  eye = jnp.eye(3)
  tau = (2 * mu[:, None, None] * jnp.einsum('nij,nkj->nik', F - R, F)
         + (lam * J * (J - 1))[:, None, None] * eye)
  A = -dt * vol[:, None, None] * 4 * inv_dx ** 2 * tau + mass[:, None,
                                                               None] * C
  off = jnp.asarray(_OFF)
  wk = w[off[:, 0], :, 0] * w[off[:, 1], :, 1] * w[off[:, 2], :, 2]
  dpos = (off[:, None, :] - fx[None]) * dx
  idx = base[None] + off[:, None, :]
  flat = ((idx[..., 0] * G + idx[..., 1]) * G + idx[..., 2]).reshape(-1)
  mom = wk[..., None] * (mass[:, None] * v + jnp.einsum('nij,knj->kni', A,
                                                        dpos))
  gm = jnp.zeros(G ** 3).at[flat].add((wk * mass[None]).reshape(-1))
  gp = jnp.zeros((G ** 3, 3)).at[flat].add(mom.reshape(-1, 3))
  has = gm > 0
  gv = gp / jnp.where(has, gm, 1.0)[:, None]
  gv = jnp.where(has[:, None], gv + dt * jnp.array([0.0, 0.0, -9.8]), 0.0)
  node_z = (jnp.arange(G ** 3) % G) * dx
  gv = jnp.where((node_z < FLOOR)[:, None], 0.0, gv)
  gvk = gv[flat].reshape(27, -1, 3)
  v = jnp.sum(wk[..., None] * gvk, 0)
  C = 4 * inv_dx ** 2 * jnp.einsum('kn,kni,knj->nij', wk, gvk, dpos)
  x = x + dt * v
  F = F + dt * jnp.einsum('nij,njk->nik', C, F)
  return x, v, C, F


def bench_naive(n, steps, repeats):
  x = jnp.asarray(make_block(n), jnp.float32)
  mu = jnp.full((n,), E / (2 * (1 + NU)))
  lam = jnp.full((n,), E * NU / ((1 + NU) * (1 - 2 * NU)))
  vol = jnp.full((n,), (GRID.dx / 2) ** 3)
  mat = (mu, lam, RHO * vol, vol)
  state = (x, jnp.tile(jnp.float32([[0, 0, -2.0]]), (n, 1)),
           jnp.zeros((n, 3, 3)), jnp.tile(jnp.eye(3), (n, 1, 1)))

  def frame(s):
    return jax.lax.fori_loop(0, steps, lambda i, c: naive_substep(c, mat, DT),
                             s)

  t0 = time.perf_counter()
  c = jax.jit(frame).lower(state).compile()
  compile_s = time.perf_counter() - t0
  sec, cpu = _median_time(c, (state,), repeats)
  out = c(state)
  return dict(variant='naive', n=n, compile_s=compile_s,
              substep_ms=1e3 * sec / steps, mpss=n * steps / sec / 1e6,
              cpu_mpss=n * steps / cpu / 1e6,
              memory_mb=_memory(c) / 2 ** 20,
              com=np.asarray(out[0]).mean(0).tolist())


def bench_grad(n, steps):
  """Cost of d(centre of mass)/dE relative to the forward rollout."""
  cfg = make_config(steps).replace(remat_frames=True)
  x = make_block(n)

  def loss(E_):
    mat = mpm.make_materials('fixed_corotated', E_, NU, RHO, num=n)
    s = mpm.init_state(x, (0.0, 0.0, -2.0), (GRID.dx / 2) ** 3, mat, cfg)
    s = mpm.make_frame(cfg)(s, mat, None)
    return jnp.mean(s.x[:, 2])

  E0 = jnp.float32(E)
  fwd = jax.jit(loss).lower(E0).compile()
  grad = jax.jit(jax.value_and_grad(loss)).lower(E0).compile()
  t_f, c_f = _median_time(fwd, (E0,), 3)
  t_g, c_g = _median_time(grad, (E0,), 3)
  _, g = grad(E0)
  return dict(variant='grad', n=n, forward_s=t_f, value_and_grad_s=t_g,
              ratio=t_g / t_f, cpu_ratio=c_g / c_f, dcom_dE=float(g),
              grad_memory_mb=_memory(grad) / 2 ** 20,
              forward_memory_mb=_memory(fwd) / 2 ** 20)


def main(argv):
  del argv
  sizes = cli.positive_ints('sizes', _SIZES.value)
  cli.check_output_file('out', _OUT.value)  # (else lost after the runs)
  info = dict(cli.machine(), devices=str(jax.devices()),
              load=os.getloadavg())
  print(json.dumps(info), flush=True)
  rows = []
  for n in sizes:
    r = bench_package(n, _STEPS.value, _REPEATS.value)
    print(json.dumps(r), flush=True)
    rows.append(r)
    for on, kw in ((_DAMPED.value, dict(viscosity=1.0)),
                   (_MAXWELL.value, dict(maxwell=True))):
      if not on:
        continue
      plain, other = [r], []
      for _ in range(2):  # alternating: a shared machine's drift cancels
        other.append(bench_package(n, _STEPS.value, _REPEATS.value, **kw))
        plain.append(bench_package(n, _STEPS.value, _REPEATS.value))
      q = dict(other[-1], mpss=float(np.median([d['mpss'] for d in other])),
               cpu_mpss=float(np.median([d['cpu_mpss'] for d in other])))
      q['ratio_vs_plain'] = q['mpss'] / float(np.median(
        [p['mpss'] for p in plain]))
      print(json.dumps(q), flush=True)
      rows.append(q)
    if _NAIVE.value:
      q = bench_naive(n, _STEPS.value, _REPEATS.value)
      q['ratio_vs_naive'] = r['mpss'] / q['mpss']
      q['cpu_ratio_vs_naive'] = r['cpu_mpss'] / q['cpu_mpss']
      print(json.dumps(q), flush=True)
      rows.append(q)
  if _GRAD.value:
    g = bench_grad(sizes[0], _STEPS.value)
    print(json.dumps(g), flush=True)
    rows.append(g)
  info['load_end'] = os.getloadavg()
  print('\n| N | variant | M particle-substeps/s (wall) | per CPU-second | '
        'ms/substep | compile [s] | memory [MB] |')
  print('|---|---|---|---|---|---|---|')
  for r in rows:
    if r['variant'] == 'grad':
      continue
    print(f"| {r['n']} | {r['variant']} | {r['mpss']:.3f} | "
          f"{r['cpu_mpss']:.3f} | {r['substep_ms']:.2f} | "
          f"{r['compile_s']:.1f} | {r['memory_mb']:.0f} |")
  cli.write_json(_OUT.value, dict(info=info, rows=rows))


if __name__ == '__main__':
  cli.run(main, cache_default='off')
