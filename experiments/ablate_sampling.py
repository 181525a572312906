"""Ablation: driving-particle selection at a fixed budget (PGAS vs uniform
Poisson disk vs K-means).

Two sphere shells of Gaussians (filled inside), one soft (E = 1e5 Pa) and one
stiff (E = 5e6 Pa). Reference motion: every Gaussian moved directly by a
smooth deformation field ``phi`` whose wavelength scales as ``sqrt(E)``
(elastic waves: lambda = c / f with c = sqrt(E / rho)), so the soft object
deforms on a shorter length scale. Drivers chosen by each method are moved by
``phi``; the Gaussians then follow them (:func:`physsplat_jax.deform.deform`).
Error = driven vs directly-moved Gaussians: mean centre error (relative to the
object radius) and relative Frobenius error of ``F Sigma F^T``.

This analytic field stands in for "simulate every Gaussian with MPM" until
the MPM solver (physsplat_jax/mpm) is available; see docs/sampling.md.

Usage: python experiments/ablate_sampling.py --budgets=100,200,400
"""

import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app
from absl import flags

from physsplat_jax import deform
from physsplat_jax import sampling
from physsplat_jax.types import Gaussians

_BUDGETS = flags.DEFINE_list('budgets', ['100', '200', '400'], 'driver counts')
_SEED = flags.DEFINE_integer('seed', 0, 'PRNG seed')
_NUM = flags.DEFINE_integer('num_gaussians', 1500, 'Gaussians per object')

E_OBJ = {0: 1e5, 1: 5e6}
CENTRE = {0: np.zeros(3), 1: np.array([1.5, 0.0, 0.0])}
RADIUS = 0.5


def make_scene(num, seed):
  rng = np.random.default_rng(seed)
  ms, ids = [], []
  for o in (0, 1):
    v = rng.normal(size=(num, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    ms.append(CENTRE[o] + RADIUS * v)
    ids.append(np.full(num, o))
  m = np.concatenate(ms)
  n = len(m)
  g = Gaussians(
    means=jnp.asarray(m, jnp.float32),
    log_scales=jnp.asarray(rng.uniform(-4.5, -3.5, (n, 3)), jnp.float32),
    quats=jnp.asarray(rng.normal(size=(n, 4)), jnp.float32),
    opacity_logits=jnp.full((n,), 3.0), sh=jnp.zeros((n, 1, 3)))
  return g, np.concatenate(ids).astype(np.int32)


def phi(x, obj):
  """Deformation field; wavelength 0.35 m * sqrt(E / 1e5 Pa)."""
  lam = 0.35 * jnp.sqrt(jnp.asarray([E_OBJ[0], E_OBJ[1]])[obj] / 1e5)
  k = 2 * jnp.pi / lam
  amp = 0.04
  u = amp * jnp.stack([
    jnp.sin(k * x[1] + 0.3), jnp.sin(k * x[2] + 1.1),
    jnp.sin(k * x[0] + 2.0)])
  return x + u


def run(budgets, seed, num):
  key = jax.random.PRNGKey(seed)
  g, ids = make_scene(num, seed)
  t0 = time.perf_counter()
  cand = sampling.make_candidates(
    key, g, ids, fill_config=sampling.FillConfig(grid_res=16))
  t_fill = time.perf_counter() - t0
  print(f'candidates: {len(cand.x)} ({int(cand.is_surface.sum())} Gaussians'
        f' + {int((~cand.is_surface).sum())} fill), fill {t_fill:.2f} s')
  phi_v = jax.jit(jax.vmap(phi))
  jac_v = jax.jit(jax.vmap(jax.jacfwd(phi)))
  X = g.means
  x_ref = phi_v(X, jnp.asarray(ids))
  J = jac_v(X, jnp.asarray(ids))
  cov_ref = J @ g.covariances @ jnp.swapaxes(J, -1, -2)
  cfg = sampling.PGASConfig(base_radius=0.4)
  rows = []
  for b in budgets:
    for method in ('pgas', 'uniform', 'kmeans'):
      t0 = time.perf_counter()
      d = sampling.select_drivers(key, cand, method, E=E_OBJ, config=cfg,
                                  budget=b, bisect_iters=8)
      t_sel = time.perf_counter() - t0
      n_obj = [int(np.sum(d.object_ids == o)) for o in (0, 1)]
      t0 = time.perf_counter()
      if min(n_obj) >= 4:  # bind within each object
        bind = deform.make_binding(g.means, d.x, k=min(8, min(n_obj)),
                                   gauss_object_ids=ids,
                                   driver_object_ids=d.object_ids)
      else:  # an object got < 4 drivers: borrow its neighbour's
        bind = deform.make_binding(g.means, d.x, k=8)
      t_bind = time.perf_counter() - t0
      dx = phi_v(jnp.asarray(d.x, jnp.float32), jnp.asarray(d.object_ids))
      fn = jax.jit(deform.deform)
      fn(bind, g, dx)[0].block_until_ready()
      t0 = time.perf_counter()
      means, covs, _ = fn(bind, g, dx)
      means.block_until_ready()
      t_def = time.perf_counter() - t0
      e_pos = np.linalg.norm(np.asarray(means - x_ref), axis=1) / RADIUS
      e_cov = (np.linalg.norm(np.asarray(covs - cov_ref), axis=(1, 2))
               / np.linalg.norm(np.asarray(cov_ref), axis=(1, 2)))
      n_obj = [int(np.sum(d.object_ids == o)) for o in (0, 1)]
      row = dict(budget=b, method=method, n=len(d.x), n_soft=n_obj[0],
                 n_stiff=n_obj[1],
                 pos_soft=e_pos[ids == 0].mean(),
                 pos_stiff=e_pos[ids == 1].mean(), pos_all=e_pos.mean(),
                 cov_all=np.median(e_cov), t_sel=t_sel, t_bind=t_bind,
                 t_def=t_def)
      rows.append(row)
      print('| {budget} | {method} | {n} ({n_soft}/{n_stiff}) | '
            '{pos_soft:.2e} | {pos_stiff:.2e} | {pos_all:.2e} | '
            '{cov_all:.2e} | {t_sel:.2f} | {t_bind:.3f} | '
            '{t_def:.4f} |'.format(**row), flush=True)
  return rows


def main(argv):
  del argv
  print('devices:', jax.devices())
  print('| budget | method | drivers (soft/stiff) | pos err soft | '
        'pos err stiff | pos err all | cov err (median) | select s | '
        'bind s | deform s |')
  print('|---|---|---|---|---|---|---|---|---|---|')
  run([int(b) for b in _BUDGETS.value], _SEED.value, _NUM.value)


if __name__ == '__main__':
  app.run(main)
