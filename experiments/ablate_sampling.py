"""Ablation: driving particles at a fixed budget (PGAS vs uniform vs K-means).

The issue's comparison: the error of the driven Gaussians against simulating
every Gaussian directly.

- Scenes (``--scene``), all dropped at 3 m/s onto a sticky floor under
  gravity; fixed corotated, nu = 0.3, rho = 1000 kg/m^3:

  * ``spheres``: two filled sphere shells of Gaussians (radius 0.25 m), one
    soft (jelly, E = 1e5 Pa) and one stiff (rubber, E = 2e6 Pa), apart;
  * ``soft-on-stiff``: a two-material body, a soft block (E = 1e5 Pa,
    0.3 x 0.3 x 0.15 m) resting on a stiff one (E = 2e6 Pa,
    0.4 x 0.4 x 0.25 m); they touch, so MPM moves them as one body;
  * ``leaf``: one material (E = 3e5 Pa), a thin plate (0.45 x 0.3 x
    0.03 m, thinner than a grid cell) sticking out of a thick block
    (0.3 m cube) at mid-height: geometry varies, stiffness does not;
  * ``tabletop``: the built-in scene's jelly cube (E = 1e5 Pa), rubber
    ball and metal can (both 2e6 Pa here: elastic, to keep the time step),
    scaled 2.5x;
  * ``ficus``: the built-in plant's stem (3e5 Pa) and leaves (1e5 Pa),
    scaled 2x: thin leaves on a thin stem.
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

Methods: ``pgas`` (Poisson disk, cap-first budget search), ``pgas-scaled``
(one factor on every radius), ``uniform``, ``kmeans`` (PhysDreamer, 20
Lloyd iterations), ``+lloyd`` (one Lloyd step on a Poisson disk), and
``pgas-cvt`` (allocation per object + weighted Lloyd,
:mod:`physsplat_jax.sampling.centroidal`), whose settings can follow a
colon, separated by slashes:
``pgas-cvt:density_power=0.5/weights=volume``.

Usage: python experiments/ablate_sampling.py --scene=spheres \\
  --budgets=500,1000,2000,5000 --json=/tmp/ablate.json (once per seed,
  ``--seed=N``), then ``--summarize --json=/tmp/ablate.json`` for
  ``pgas-cvt`` over ``kmeans`` per scene and budget across the seeds.
"""

import dataclasses
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app
from absl import flags

from experiments.lib import cli
from physsplat_jax import deform
from physsplat_jax import mpm
from physsplat_jax import sampling
from physsplat_jax.types import Gaussians

E_OBJ = {0: 1e5, 1: 2e6}
# E per object of each scene.
SCENE_E = {'spheres': E_OBJ, 'soft-on-stiff': E_OBJ, 'leaf': {0: 3e5, 1: 3e5},
           'tabletop': {0: 1e5, 1: 2e6, 2: 2e6}, 'ficus': {0: 3e5, 1: 1e5}}
# Built-in scenes: the objects taken (in this order, as objects 0, 1, ...)
# and the scale into the 2 m domain.
BUILTIN = {'tabletop': (('jelly cube', 'rubber ball', 'metal can'), 2.5),
           'ficus': (('stem', 'leaves'), 2.0)}
NU, RHO = 0.3, 1000.0
RADIUS = 0.25  # error unit: distances are reported relative to it
CENTRE = {0: np.array([0.65, 1.0, 0.45]), 1: np.array([1.35, 1.0, 0.45])}
V0 = (0.0, 0.0, -3.0)
FLOOR_Z = 0.15
FRAME_DT = 1.0 / 60.0


def _quat_to(v):
  """Quaternions (w, x, y, z) of the rotations taking e3 to the unit v."""
  axis = np.cross([0.0, 0.0, 1.0], v)
  s = np.linalg.norm(axis, axis=1, keepdims=True)
  half = 0.5 * np.arctan2(s[:, 0], v[:, 2])
  ax = np.where(s > 1e-9, axis / np.maximum(s, 1e-12), [1.0, 0, 0])
  return np.c_[np.cos(half), np.sin(half)[:, None] * ax]


def _box_surface(rng, lo, hi, num):
  """``num`` points uniform by area on a box's surface, and their normals."""
  lo, hi = np.asarray(lo, float), np.asarray(hi, float)
  ext = hi - lo
  areas = np.array([ext[1] * ext[2], ext[0] * ext[2], ext[0] * ext[1]])
  face = rng.choice(6, size=num, p=np.repeat(areas, 2) / (2 * areas.sum()))
  ax, side = face // 2, face % 2
  p = lo + rng.uniform(size=(num, 3)) * ext
  p[np.arange(num), ax] = np.where(side == 1, hi[ax], lo[ax])
  nrm = np.zeros((num, 3))
  nrm[np.arange(num), ax] = np.where(side == 1, 1.0, -1.0)
  return p, nrm


def _boxes(rng, boxes, num):
  """Surface points of (lo, hi, object) boxes, ``num`` per 0.5 m^2 of area;
  points inside another box of the same object are dropped."""
  ms, ns, ids = [], [], []
  for lo, hi, o in boxes:
    e = np.subtract(hi, lo)
    area = 2 * (e[0] * e[1] + e[1] * e[2] + e[0] * e[2])
    p, nrm = _box_surface(rng, lo, hi, max(int(num * area / 0.5), 200))
    keep = np.ones(len(p), bool)
    for lo2, hi2, o2 in boxes:
      if (lo2, hi2) != (lo, hi) and o2 == o:
        keep &= ~np.all((p > np.add(lo2, 1e-9)) & (p < np.subtract(hi2, 1e-9)),
                        axis=1)
    ms.append(p[keep])
    ns.append(nrm[keep])
    ids.append(np.full(keep.sum(), o))
  return np.concatenate(ms), np.concatenate(ns), np.concatenate(ids)


def _builtin(name):
  """Objects of a built-in scene, scaled by ``BUILTIN[name][1]`` and set
  down above the floor in the middle of the domain (no other change)."""
  from physsplat_jax import scenes  # noqa: PLC0415 - only for these scenes
  sc = scenes.load_scene(name)
  names, scale = BUILTIN[name]
  oid = np.asarray(sc.object_ids)
  rows, ids = [], []
  for i, nm in enumerate(names):
    r = np.nonzero(oid == sc.object_names.index(nm))[0]
    rows.append(r)
    ids.append(np.full(len(r), i))
  g = sc.gaussians.subset(np.concatenate(rows))
  m = np.asarray(g.means, np.float64) * scale
  lo, hi = m.min(0), m.max(0)
  shift = np.array([1.0, 1.0, FLOOR_Z + 0.05]) - [
    0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]]
  g = g.replace(means=jnp.asarray(m + shift, jnp.float32),
                log_scales=g.log_scales + np.log(scale))
  return g, np.concatenate(ids).astype(np.int32)


def make_scene(num, seed, scene='spheres'):
  """Flat Gaussians tangent to the surface of the scene's objects."""
  rng = np.random.default_rng(seed)
  if scene == 'spheres':
    ms, ids, ns = [], [], []
    for o in (0, 1):
      v = rng.normal(size=(num, 3))
      v /= np.linalg.norm(v, axis=1, keepdims=True)
      ms.append(CENTRE[o] + RADIUS * v)
      ns.append(v)
      ids.append(np.full(num, o))
    m, nrm, ids = map(np.concatenate, (ms, ns, ids))
    spacing = RADIUS * np.sqrt(4 * np.pi / num)
  elif scene == 'soft-on-stiff':
    z0 = FLOOR_Z + 0.05
    m, nrm, ids = _boxes(rng, [
      ((0.8, 0.8, z0 + 0.25), (1.1, 1.1, z0 + 0.4), 0),  # soft top
      ((0.75, 0.75, z0), (1.15, 1.15, z0 + 0.25), 1)], num)  # stiff base
    spacing = np.sqrt(0.5 / num)
  elif scene == 'leaf':
    z0 = FLOOR_Z + 0.05
    m, nrm, ids = _boxes(rng, [
      ((0.55, 0.85, z0 + 0.135), (1.0, 1.15, z0 + 0.165), 0),  # leaf
      ((1.0, 0.85, z0), (1.3, 1.15, z0 + 0.3), 1)], num)  # trunk
    spacing = np.sqrt(0.5 / num)
  elif scene in BUILTIN:
    return _builtin(scene)
  else:
    raise ValueError(f"scene={scene!r}; use one of {sorted(SCENE_E)}")
  qs = _quat_to(nrm)
  n = len(m)
  ls = np.log(0.5 * spacing) + rng.normal(0.0, 0.1, (n, 3))
  ls[:, 2] -= 2.0
  g = Gaussians(
    means=jnp.asarray(m, jnp.float32), log_scales=jnp.asarray(ls, jnp.float32),
    quats=jnp.asarray(qs, jnp.float32),
    opacity_logits=jnp.full((n,), 3.0), sh=jnp.zeros((n, 1, 3)))
  return g, ids.astype(np.int32)


def sim_config(grid_res, substeps):
  return mpm.SimConfig(
    grid=mpm.GridSpec(res=grid_res, lower=(0.0, 0.0, 0.0), size=2.0),
    dt=FRAME_DT / substeps, substeps_per_frame=substeps,
    models=('fixed_corotated',),
    boundary_conditions=(mpm.SurfaceCollider(point=(0.0, 0.0, FLOOR_Z),
                                             normal=(0.0, 0.0, 1.0)),))


def materials_for(object_ids, e_obj=None):
  e_obj = E_OBJ if e_obj is None else e_obj
  E = np.array([e_obj[int(o)] for o in object_ids], np.float32)
  return mpm.make_materials('fixed_corotated', E=jnp.asarray(E), nu=NU,
                            rho=RHO)


def simulate(x0, volume, object_ids, config, num_frames, e_obj=None):
  """MPM rollout; returns (xs (T+1, N, 3), compile s, run s)."""
  mats = materials_for(object_ids, e_obj)
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


def _cvt_config(opts: str) -> sampling.CVTConfig:
  """The CVTConfig of ``pgas-cvt:field=value/...``'s ``opts``."""
  kw = {}
  for item in filter(None, opts.split('/')):
    k, _, v = item.partition('=')
    f = {f.name: f for f in dataclasses.fields(sampling.CVTConfig)}[k]
    kw[k] = v if f.type == 'str' else type(getattr(
      sampling.CVTConfig(), k))(float(v))
  return sampling.CVTConfig(**kw)


def check_methods(methods) -> None:
  """Each ``--methods`` value is one :func:`_select` knows, or a usage
  error naming it (an unknown one was found after the reference run, a
  bad ``pgas-cvt`` field was a KeyError traceback)."""
  for method in methods:
    base, _, opts = method.partition(':')
    if base == 'pgas-cvt':
      try:
        _cvt_config(opts)
      except (KeyError, ValueError) as e:
        fields = ', '.join(f.name for f in
                           dataclasses.fields(sampling.CVTConfig))
        raise cli.usage_error(
          f'--methods: {method!r}: {e}; give pgas-cvt:FIELD=VALUE/... with '
          f'fields of CVTConfig ({fields})') from None
      continue
    name, _, extra = base.partition('+')
    if (name not in ('pgas', 'pgas-scaled', 'uniform', 'kmeans')
        or extra not in ('', 'lloyd') or opts):
      raise cli.usage_error(
        f'--methods: unknown {method!r}; use pgas, pgas-scaled, uniform, '
        'kmeans (each with +lloyd) or pgas-cvt[:FIELD=VALUE/...]')


def _select(key, cand, method, e_obj, cfg, budget):
  """Drivers of one method (see the module docstring for the names)."""
  base, _, opts = method.partition(':')
  if base == 'pgas-cvt':
    return sampling.select_drivers(key, cand, 'pgas-cvt', E=e_obj,
                                   config=cfg, budget=budget,
                                   cvt=_cvt_config(opts))
  base, _, extra = base.partition('+')
  name = base.split('-')[0]
  # 'pgas-scaled': one factor on every PGAS radius for the budget (the base
  # radius is not kept as an upper bound); '+lloyd': one Lloyd step.
  kw = {} if name == 'kmeans' else dict(
    pgas_cap_first=base != 'pgas-scaled',
    lloyd_steps=1 if extra == 'lloyd' else 0)
  return sampling.select_drivers(key, cand, name, E=e_obj, config=cfg,
                                 budget=budget, **kw)


def run(budgets, seed=0, num=3000, grid_res=24, num_frames=12,
        methods=('pgas', 'pgas-scaled', 'uniform', 'kmeans'),
        particles_per_cell=4.0, fill_res=24, log=print, scene='spheres'):
  """Runs the ablation; returns a list of result rows (dicts).

  Row keys: ``n_0``/``n_1`` drivers and ``err_0``/``err_1`` mean errors of
  objects 0 and 1 (spheres: soft/stiff; soft-on-stiff: soft top/stiff base;
  leaf: leaf/trunk), ``err_all`` over all Gaussians and frames,
  ``err_last`` at the last frame, selection and simulation seconds.
  """
  key = jax.random.PRNGKey(seed)
  e_obj = SCENE_E[scene]
  g, ids = make_scene(num, seed, scene)
  t0 = time.perf_counter()
  cand = sampling.make_candidates(
    key, g, ids, fill_config=sampling.FillConfig(grid_res=fill_res))
  t_cand = time.perf_counter() - t0
  k_g = int(cand.is_surface.sum())
  log(f'scene {scene}: candidates: {len(cand.x)} ({k_g} Gaussians + '
      f'{len(cand.x) - k_g} fill), {t_cand:.2f} s')
  mats = materials_for(cand.object_ids, e_obj)
  dx = 2.0 / grid_res
  substeps = mpm.choose_substeps(dx, FRAME_DT, mats, max_speed=4.0)
  config = sim_config(grid_res, substeps)
  log(f'grid {grid_res}^3 (dx = {dx:.4f} m), {substeps} substeps/frame, '
      f'{num_frames} frames')
  xs_ref, tc, tr = simulate(cand.x, cand.volume, cand.object_ids, config,
                            num_frames, e_obj)
  log(f'reference: {len(cand.x)} particles, compile {tc:.1f} s, '
      f'run {tr:.2f} s')
  ref = xs_ref[:, :k_g]  # the Gaussian centres come first
  drop = ref[-1, :, 2].mean() - ref[0, :, 2].mean()
  log(f'mean Gaussian drop {drop:.3f} m')
  cfg = sampling.PGASConfig(
    base_radius=dx * (1.24 / particles_per_cell) ** (1.0 / 3.0))
  deform_v = jax.jit(jax.vmap(lambda b, x: deform.deform(b, g, x)[0],
                              in_axes=(None, 0)))
  rows = [dict(scene=scene, budget=len(cand.x), method='all (reference)',
               n=len(cand.x), n_0=int(np.sum(cand.object_ids == 0)),
               n_1=int(np.sum(cand.object_ids == 1)), err_0=0.0,
               err_1=0.0, err_all=0.0, err_last=0.0, t_sel=0.0,
               t_sim=tr)]
  for b in budgets:
    for method in methods:
      t0 = time.perf_counter()
      d = _select(key, cand, method, e_obj, cfg, b)
      t_sel = time.perf_counter() - t0
      n_obj = [int(np.sum(d.object_ids == o)) for o in sorted(e_obj)]
      if min(n_obj) < 4:
        log(f'| {b} | {method} | {len(d.x)} ({n_obj[0]}/{n_obj[1]}) | '
            'an object has < 4 drivers: cannot bind |')
        continue
      x0, vol, ob = _pad(d, max(b, len(d.x)))
      xs, tc, tr = simulate(x0, vol, ob, config, num_frames, e_obj)
      bind = deform.make_binding(g.means, d.x, k=min(8, min(n_obj)),
                                 gauss_object_ids=ids,
                                 driver_object_ids=d.object_ids)
      means = np.asarray(deform_v(bind, jnp.asarray(xs[:, :len(d.x)])))
      err = np.linalg.norm(means - ref, axis=-1) / RADIUS  # (T+1, K)
      row = dict(scene=scene, budget=b, method=method, n=len(d.x),
                 n_0=n_obj[0], n_1=n_obj[1],
                 err_0=float(err[:, ids == 0].mean()),
                 err_1=float(err[:, ids == 1].mean()),
                 n_objs=n_obj, err_objs=[float(err[:, ids == o].mean())
                                         for o in sorted(e_obj)],
                 err_all=float(err.mean()), err_last=float(err[-1].mean()),
                 t_sel=t_sel, t_sim=tr)
      rows.append(row)
      log('| {budget} | {method} | {n} ({n_0}/{n_1}) | '
          '{err_0:.2e} | {err_1:.2e} | {err_all:.2e} | '
          '{err_last:.2e} | {t_sel:.2f} | {t_sim:.2f} |'.format(**row))
  return rows


def summarize(rows, method: str = 'pgas-cvt', baseline: str = 'kmeans',
              log=print) -> list[dict]:
  """Per (scene, budget): ``method``'s error over ``baseline``'s, over seeds.

  A single rollout's error moves by up to 1.5x with the random start of the
  placement, so one seed decides nothing; this pairs the two methods' rows
  of each (scene, seed, budget) and reports the geometric mean of the
  ratios of ``err_all`` with a 95 % interval (Student t on the log ratios)
  and how many seeds favour ``method``.

  Args:
    rows: rows of :func:`run` with ``seed`` set (the ``--json`` file).
    method, baseline: method names as in the rows.
    log: printer of the Markdown table (None: silent).

  Returns:
    one dict per (scene, budget): scene, budget, seeds, ratio, lo, hi, wins.
  """
  from scipy import stats  # pylint: disable=import-outside-toplevel
  err = {}
  for r in rows:
    err[(r['scene'], r.get('seed', 0), int(r['budget']), r['method'])] = (
      r['err_all'])
  cells = sorted({(sc, b) for sc, _, b, m in err if m == method})
  out = []
  if log:
    log(f'| scene | budget | seeds | {method} / {baseline} (geometric mean) '
        '| 95 % interval | seeds where better |')
    log('|---|---|---|---|---|---|')
  for sc, b in cells:
    seeds = sorted(s for s2, s, b2, m in err
                   if (s2, b2, m) == (sc, b, method)
                   and (sc, s, b, baseline) in err)
    if not seeds:
      continue
    lr = np.log([err[(sc, s, b, method)] / err[(sc, s, b, baseline)]
                 for s in seeds])
    mean = float(np.mean(lr))
    half = (float(stats.t.ppf(0.975, len(lr) - 1) * np.std(lr, ddof=1)
                  / np.sqrt(len(lr))) if len(lr) > 1 else float('inf'))
    row = dict(scene=sc, budget=b, seeds=len(seeds), ratio=np.exp(mean),
               lo=np.exp(mean - half), hi=np.exp(mean + half),
               wins=int(np.sum(lr < 0)))
    out.append(row)
    if log:
      log('| {scene} | {budget} | {seeds} | {ratio:.2f} | {lo:.2f}-{hi:.2f} '
          '| {wins} |'.format(**row))
  return out


def _define_flags():
  """Flags, defined only when run as a script (importing this module from
  tests must not register flags that other experiment scripts also use)."""
  return dict(
    budgets=flags.DEFINE_list('budgets', ['500', '1000', '2000'],
                              'driver counts (both objects together)'),
    seed=flags.DEFINE_integer('seed', 0, 'PRNG seed'),
    num=flags.DEFINE_integer('num_gaussians', 3000,
                             'Gaussians per sphere, or per 0.5 m^2 of box '
                             'surface'),
    fill_res=flags.DEFINE_integer('fill_res', 24,
                                  'fill grid cells per object'),
    grid_res=flags.DEFINE_integer('grid_res', 24,
                                  'MPM grid cells per axis (2 m)'),
    num_frames=flags.DEFINE_integer('num_frames', 12, 'frames of 1/60 s'),
    methods=flags.DEFINE_list(
      'methods', ['pgas', 'pgas-scaled', 'uniform', 'kmeans'],
      "driver selection methods ('pgas-scaled': pgas_cap_first=False; "
      "'+lloyd': lloyd_steps=1; 'pgas-cvt[:field=value/...]': allocation "
      "+ weighted Lloyd with those CVTConfig fields)"),
    scene=flags.DEFINE_enum('scene', 'spheres', sorted(SCENE_E), 'scene'),
    json=flags.DEFINE_string('json', '', 'append the rows to this JSON '
                             'file (a list of rows)'),
    summarize=flags.DEFINE_bool(
      'summarize', False, 'run nothing: print, from the rows in --json, '
      'pgas-cvt / kmeans per scene and budget over the seeds'),
    summarize_method=flags.DEFINE_string(
      'summarize_method', 'pgas-cvt', 'with --summarize: the method (as '
      "named in the rows, e.g. "
      "'pgas-cvt:thinness=occupancy/geom_ref=0.6/geom_max=3') compared "
      'with kmeans'),
    ppc=flags.DEFINE_float('particles_per_cell', 4.0,
                           'sets the base radius dx (1.24 / ppc)^(1/3), as '
                           'the pipeline does'))


def main(argv, f):
  del argv
  if f['summarize'].value:
    if not f['json'].value:
      raise app.UsageError('--summarize reads the rows of --json=FILE')
    if not os.path.isfile(f['json'].value):
      raise cli.usage_error(f'--json={f["json"].value}: no such file; give '
                            'the rows of earlier runs (--json=FILE)')
    with open(f['json'].value) as fh:
      summarize(json.load(fh), method=f['summarize_method'].value)
    return
  # The flags before the reference run (--budgets=abc was a traceback, a
  # bad --json's folder lost the rows after every run).
  budgets = cli.positive_ints('budgets', f['budgets'].value)
  check_methods(f['methods'].value)
  cli.check_output_file('json', f['json'].value)
  print('devices:', jax.devices())
  print('| budget | method | drivers (obj 0/obj 1) | err obj 0 | err obj 1 | '
        'err all | err last frame | select s | simulate s |')
  print('|---|---|---|---|---|---|---|---|---|')
  rows = run(budgets, f['seed'].value,
             f['num'].value, f['grid_res'].value, f['num_frames'].value,
             tuple(f['methods'].value), f['ppc'].value, f['fill_res'].value,
             log=lambda s: print(s, flush=True), scene=f['scene'].value)
  if f['json'].value:
    path = f['json'].value
    try:
      with open(path) as fh:
        old = json.load(fh)
    except FileNotFoundError:
      old = []
    for r in rows:
      r['seed'] = f['seed'].value
    # (through a temporary file: a failed write keeps the earlier rows)
    cli.write_json(path, old + rows)


if __name__ == '__main__':
  _f = _define_flags()
  cli.run(lambda argv: main(argv, _f))
