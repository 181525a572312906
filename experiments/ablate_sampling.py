"""Ablation: driving particles at a fixed budget (PGAS vs uniform vs K-means).

The issue's comparison: the error of the driven Gaussians against simulating
every Gaussian directly.

- Scene: two filled sphere shells of Gaussians (radius 0.25 m) dropped at
  3 m/s onto a sticky floor under gravity, one soft (jelly, E = 1e5 Pa) and
  one stiff (rubber, E = 2e6 Pa); fixed corotated, nu = 0.3,
  rho = 1000 kg/m^3.
- Reference: MLS-MPM (``physsplat_jax.mpm``) on *every* candidate, i.e.
  every Gaussian centre plus the interior fill particles; the Gaussians'
  reference trajectory is that of their own particles.
- Driven: the same solver, grid and time step on the drivers chosen by each
  method (the Poisson disks' budget search, K-means with exactly the
  budget), each driver with the Voronoi volume of its candidates (so the
  mass is the same); every Gaussian then follows its ``k = 8`` nearest
  drivers of its own object (``physsplat_jax.deform``, weighted affine fit).
- Error: Gaussian-centre distance to the reference relative to the sphere
  radius, averaged over the Gaussians and over all frames (and at the last
  frame), per object; times of selection, compile and simulation.

Drivers are padded with zero-volume (massless, stressless) copies up to the
budget so that every method at a budget shares one compiled rollout.

Usage: python experiments/ablate_sampling.py --budgets=500,1000,2000
"""

import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app
from absl import flags

from physsplat_jax import deform
from physsplat_jax import mpm
from physsplat_jax import sampling
from physsplat_jax.types import Gaussians

E_OBJ = {0: 1e5, 1: 2e6}
NU, RHO = 0.3, 1000.0
RADIUS = 0.25
CENTRE = {0: np.array([0.65, 1.0, 0.45]), 1: np.array([1.35, 1.0, 0.45])}
V0 = (0.0, 0.0, -3.0)
FLOOR_Z = 0.15
FRAME_DT = 1.0 / 60.0


def make_scene(num, seed):
  """Two sphere shells of flat Gaussians tangent to the surface."""
  rng = np.random.default_rng(seed)
  ms, ids, qs = [], [], []
  for o in (0, 1):
    v = rng.normal(size=(num, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    ms.append(CENTRE[o] + RADIUS * v)
    ids.append(np.full(num, o))
    # Rotation taking e3 to the normal v (the thin axis is the normal).
    axis = np.cross([0.0, 0.0, 1.0], v)
    s = np.linalg.norm(axis, axis=1, keepdims=True)
    half = 0.5 * np.arctan2(s[:, 0], v[:, 2])
    ax = np.where(s > 1e-9, axis / np.maximum(s, 1e-12), [1.0, 0, 0])
    qs.append(np.c_[np.cos(half), np.sin(half)[:, None] * ax])
  m = np.concatenate(ms)
  n = len(m)
  spacing = RADIUS * np.sqrt(4 * np.pi / num)
  ls = np.log(0.5 * spacing) + rng.normal(0.0, 0.1, (n, 3))
  ls[:, 2] -= 2.0
  g = Gaussians(
    means=jnp.asarray(m, jnp.float32), log_scales=jnp.asarray(ls, jnp.float32),
    quats=jnp.asarray(np.concatenate(qs), jnp.float32),
    opacity_logits=jnp.full((n,), 3.0), sh=jnp.zeros((n, 1, 3)))
  return g, np.concatenate(ids).astype(np.int32)


def sim_config(grid_res, substeps):
  return mpm.SimConfig(
    grid=mpm.GridSpec(res=grid_res, lower=(0.0, 0.0, 0.0), size=2.0),
    dt=FRAME_DT / substeps, substeps_per_frame=substeps,
    models=('fixed_corotated',),
    boundary_conditions=(mpm.SurfaceCollider(point=(0.0, 0.0, FLOOR_Z),
                                             normal=(0.0, 0.0, 1.0)),))


def materials_for(object_ids):
  E = np.array([E_OBJ[int(o)] for o in object_ids], np.float32)
  return mpm.make_materials('fixed_corotated', E=jnp.asarray(E), nu=NU,
                            rho=RHO)


def simulate(x0, volume, object_ids, config, num_frames):
  """MPM rollout; returns (xs (T+1, N, 3), compile s, run s)."""
  mats = materials_for(object_ids)
  state = mpm.init_state(jnp.asarray(x0, jnp.float32), V0,
                         jnp.asarray(volume, jnp.float32), mats, config)
  fn = jax.jit(lambda s, m: mpm.rollout(s, m, None, config, num_frames)[1])
  t0 = time.perf_counter()
  compiled = fn.lower(state, mats).compile()
  t_compile = time.perf_counter() - t0
  t0 = time.perf_counter()
  xs = compiled(state, mats)
  xs.block_until_ready()
  t_run = time.perf_counter() - t0
  xs = np.asarray(xs)
  if not np.all(np.isfinite(xs)):
    raise RuntimeError('MPM rollout produced NaN/inf; lower the time step')
  return xs, t_compile, t_run


def _pad(d, budget):
  """Drivers padded to ``budget`` rows with massless copies of driver 0."""
  n = len(d.x)
  x = np.concatenate([d.x, np.repeat(d.x[:1], budget - n, 0)])
  vol = np.concatenate([d.volume, np.zeros(budget - n)])
  ob = np.concatenate([d.object_ids, np.repeat(d.object_ids[:1], budget - n)])
  return x, vol, ob


def run(budgets, seed=0, num=3000, grid_res=24, num_frames=12,
        methods=('pgas', 'pgas-scaled', 'uniform', 'kmeans'),
        particles_per_cell=4.0, fill_res=24, log=print):
  """Runs the ablation; returns a list of result rows (dicts)."""
  key = jax.random.PRNGKey(seed)
  g, ids = make_scene(num, seed)
  t0 = time.perf_counter()
  cand = sampling.make_candidates(
    key, g, ids, fill_config=sampling.FillConfig(grid_res=fill_res))
  t_cand = time.perf_counter() - t0
  k_g = int(cand.is_surface.sum())
  log(f'candidates: {len(cand.x)} ({k_g} Gaussians + '
      f'{len(cand.x) - k_g} fill), {t_cand:.2f} s')
  mats = materials_for(cand.object_ids)
  dx = 2.0 / grid_res
  substeps = mpm.choose_substeps(dx, FRAME_DT, mats, max_speed=4.0)
  config = sim_config(grid_res, substeps)
  log(f'grid {grid_res}^3 (dx = {dx:.4f} m), {substeps} substeps/frame, '
      f'{num_frames} frames')
  xs_ref, tc, tr = simulate(cand.x, cand.volume, cand.object_ids, config,
                            num_frames)
  log(f'reference: {len(cand.x)} particles, compile {tc:.1f} s, '
      f'run {tr:.2f} s')
  ref = xs_ref[:, :k_g]  # the Gaussian centres come first
  drop = ref[-1, :, 2].mean() - ref[0, :, 2].mean()
  log(f'mean Gaussian drop {drop:.3f} m')
  cfg = sampling.PGASConfig(
    base_radius=dx * (1.24 / particles_per_cell) ** (1.0 / 3.0))
  deform_v = jax.jit(jax.vmap(lambda b, x: deform.deform(b, g, x)[0],
                              in_axes=(None, 0)))
  rows = [dict(budget=len(cand.x), method='all (reference)',
               n=len(cand.x), n_soft=int(np.sum(cand.object_ids == 0)),
               n_stiff=int(np.sum(cand.object_ids == 1)), err_soft=0.0,
               err_stiff=0.0, err_all=0.0, err_last=0.0, t_sel=0.0,
               t_sim=tr)]
  for b in budgets:
    for method in methods:
      t0 = time.perf_counter()
      # 'pgas-scaled': one factor on every PGAS radius for the budget
      # (the base radius is not kept as an upper bound).
      # 'pgas+lloyd': one Lloyd step (drivers at their cells' centroids).
      base, _, extra = method.partition('+')
      name = base.split('-')[0]
      kw = {} if name == 'kmeans' else dict(
        pgas_cap_first=base != 'pgas-scaled',
        lloyd_steps=1 if extra == 'lloyd' else 0)
      d = sampling.select_drivers(key, cand, name, E=E_OBJ, config=cfg,
                                  budget=b, **kw)
      t_sel = time.perf_counter() - t0
      n_obj = [int(np.sum(d.object_ids == o)) for o in (0, 1)]
      if min(n_obj) < 4:
        log(f'| {b} | {method} | {len(d.x)} ({n_obj[0]}/{n_obj[1]}) | '
            'an object has < 4 drivers: cannot bind |')
        continue
      x0, vol, ob = _pad(d, max(b, len(d.x)))
      xs, tc, tr = simulate(x0, vol, ob, config, num_frames)
      bind = deform.make_binding(g.means, d.x, k=min(8, min(n_obj)),
                                 gauss_object_ids=ids,
                                 driver_object_ids=d.object_ids)
      means = np.asarray(deform_v(bind, jnp.asarray(xs[:, :len(d.x)])))
      err = np.linalg.norm(means - ref, axis=-1) / RADIUS  # (T+1, K)
      row = dict(budget=b, method=method, n=len(d.x), n_soft=n_obj[0],
                 n_stiff=n_obj[1], err_soft=err[:, ids == 0].mean(),
                 err_stiff=err[:, ids == 1].mean(), err_all=err.mean(),
                 err_last=err[-1].mean(), t_sel=t_sel, t_sim=tr)
      rows.append(row)
      log('| {budget} | {method} | {n} ({n_soft}/{n_stiff}) | '
          '{err_soft:.2e} | {err_stiff:.2e} | {err_all:.2e} | '
          '{err_last:.2e} | {t_sel:.2f} | {t_sim:.2f} |'.format(**row))
  return rows


def _define_flags():
  """Flags, defined only when run as a script (importing this module from
  tests must not register flags that other experiment scripts also use)."""
  return dict(
    budgets=flags.DEFINE_list('budgets', ['500', '1000', '2000'],
                              'driver counts (both objects together)'),
    seed=flags.DEFINE_integer('seed', 0, 'PRNG seed'),
    num=flags.DEFINE_integer('num_gaussians', 3000, 'Gaussians per object'),
    fill_res=flags.DEFINE_integer('fill_res', 24,
                                  'fill grid cells per object'),
    grid_res=flags.DEFINE_integer('grid_res', 24,
                                  'MPM grid cells per axis (2 m)'),
    num_frames=flags.DEFINE_integer('num_frames', 12, 'frames of 1/60 s'),
    methods=flags.DEFINE_list(
      'methods', ['pgas', 'pgas-scaled', 'uniform', 'kmeans'],
      "driver selection methods ('pgas-scaled': pgas_cap_first=False; "
      "'+lloyd': lloyd_steps=1)"),
    ppc=flags.DEFINE_float('particles_per_cell', 4.0,
                           'sets the base radius dx (1.24 / ppc)^(1/3), as '
                           'the pipeline does'))


def main(argv, f):
  del argv
  print('devices:', jax.devices())
  print('| budget | method | drivers (soft/stiff) | err soft | err stiff | '
        'err all | err last frame | select s | simulate s |')
  print('|---|---|---|---|---|---|---|---|---|')
  run([int(b) for b in f['budgets'].value], f['seed'].value, f['num'].value,
      f['grid_res'].value, f['num_frames'].value, tuple(f['methods'].value),
      f['ppc'].value, f['fill_res'].value,
      log=lambda s: print(s, flush=True))


if __name__ == '__main__':
  _f = _define_flags()
  app.run(lambda argv: main(argv, _f))
