"""Validates the MLS-MPM solver against analytic solutions (docs/validation.md).

Cases (each at two resolutions unless --quick):

- free_fall: centre of mass vs x0 + v0 t + g t^2 / 2.
- bar_mode: first longitudinal mode of a free-free elastic bar,
  f = sqrt(E / rho) / (2 L).
- cantilever, cantilever_slender: first bending mode of a clamped
  cantilever (L/h = 5, 10) vs Euler-Bernoulli,
  f = 1.8751^2 / (2 pi L^2) sqrt(E I / (rho A)), and Timoshenko.
- cantilever_pg: the same through a PhysGaussian config (a lattice of
  Gaussians, a ``cuboid`` clamp, gravity), L/h = 5 and 10.
- sand_slope: flank slope of a collapsed Drucker-Prager sand column vs the
  friction angle (two angles).
- contact: blocks of jelly, metal, sand and a rigid box resting on a plane
  ('separate' and 'sticky') placed between grid nodes: rest height of each
  underside [cells].
- repose: quasi-static angle of repose of a sand pile vs the friction
  angle (20, 30 and 40 deg).

python -m experiments.validate_physics [--cases=free_fall,bar_mode] [--quick]
  [--out=results.json]
"""

import json
import math
import time

import numpy as np
from absl import flags
from absl import logging

from experiments.lib import cli
from physsplat_jax import mpm

_CASES = flags.DEFINE_list(
  'cases', ['free_fall', 'bar_mode', 'cantilever', 'sand_slope', 'contact'],
  'cases to run; also cantilever_slender, cantilever_pg and repose (the '
  'long ones, not in the default)')
_QUICK = flags.DEFINE_bool('quick', False, 'one coarse resolution per case')
_OUT = cli.define_out(None, 'optional JSON output path')
_REPOSE_SECONDS = flags.DEFINE_float(
  'repose_seconds', 7.0, 'simulated time of the repose case [s] (the '
  'piles creep for several seconds: at 4 s the angles were up to 2.6 deg '
  'steeper)')
_PHIS = flags.DEFINE_list('phis', ['20', '30', '40'],
                          'friction angles of the repose case [deg]')


def lattice(lo, hi, spacing):
  """Particles on a lattice filling the box [lo, hi] (cell centres)."""
  lo, hi = np.asarray(lo, float), np.asarray(hi, float)
  n = np.maximum(np.round((hi - lo) / spacing).astype(int), 1)
  axes = [lo[d] + (np.arange(n[d]) + 0.5) * (hi[d] - lo[d]) / n[d]
          for d in range(3)]
  x = np.stack(np.meshgrid(*axes, indexing='ij'), -1).reshape(-1, 3)
  return x, np.prod((hi - lo) / n)


def frequency(t, y):
  """Mean frequency from the zero crossings of y - mean(y) [Hz]."""
  y = np.asarray(y) - np.mean(y)
  s = np.sign(y)
  idx = np.flatnonzero(s[:-1] * s[1:] < 0)
  tz = t[idx] - y[idx] * (t[idx + 1] - t[idx]) / (y[idx + 1] - y[idx])
  if len(tz) < 3:
    return float('nan')
  return 0.5 * (len(tz) - 1) / (tz[-1] - tz[0])


def free_fall(res):
  grid = mpm.GridSpec(res=res, size=1.0)
  g = np.array([0.0, 0.0, -9.8])
  v0 = np.array([0.5, 0.0, 1.0])
  x, vol = lattice((0.3, 0.4, 0.3), (0.4, 0.5, 0.4), grid.dx / 2)
  mat = mpm.make_materials('fixed_corotated', 1e5, 0.3, 1000.0, num=len(x))
  frame_dt, frames = 0.02, 10
  n = mpm.choose_substeps(grid.dx, frame_dt, mat)
  cfg = mpm.SimConfig(grid=grid, dt=frame_dt / n, substeps_per_frame=n,
                      gravity=tuple(g))
  s = mpm.init_state(x, v0, vol, mat, cfg)
  r = mpm.run(s, mat, None, cfg, frames)
  t = r.times
  com = r.positions.mean(1)
  ref = x.mean(0) + v0 * t[:, None] + 0.5 * g * t[:, None] ** 2
  err = float(np.abs(com - ref).max())
  # Symplectic Euler: x_n = x0 + v0 t + g t^2/2 + g t dt/2 exactly.
  disc = ref + 0.5 * g * t[:, None] * cfg.dt
  return dict(
    case='free_fall', res=res, particles=len(x), dt=cfg.dt,
    metric='max |com - analytic| [m]', value=err,
    reference='x0 + v0 t + g t^2/2',
    rel_error=err / float(np.abs(ref - x.mean(0)).max()),
    discrete_error=float(np.abs(com - disc).max()),
    seconds=r.run_s + r.compile_s)


def bar_mode(res):
  grid = mpm.GridSpec(res=res, size=1.0)
  E, rho, nu = 1e5, 1000.0, 0.3
  L, h = 0.5, 0.06
  lo = np.array([0.25, 0.47, 0.47])
  x, vol = lattice(lo, lo + [L, h, h], grid.dx / 2)
  xi = (x[:, 0] - lo[0]) / L
  v = np.zeros_like(x)
  v[:, 0] = 0.02 * np.cos(np.pi * xi)
  mat = mpm.make_materials('fixed_corotated', E, nu, rho, num=len(x))
  f_ref = math.sqrt(E / rho) / (2 * L)
  frame_dt = 1.0 / (f_ref * 40)
  n = mpm.choose_substeps(grid.dx, frame_dt, mat)
  cfg = mpm.SimConfig(grid=grid, dt=frame_dt / n, substeps_per_frame=n,
                      gravity=(0, 0, 0))
  s = mpm.init_state(x, v, vol, mat, cfg)
  frames = int(3.2 / f_ref / frame_dt)
  end = x[:, 0] > lo[0] + L - grid.dx / 2
  r = mpm.run(s, mat, None, cfg, frames)
  y = r.positions[:, end, 0].mean(1) - r.positions[:, :, 0].mean(1)
  f = frequency(r.times, y)
  return dict(
    case='bar_mode', res=res, particles=len(x), dt=cfg.dt,
    metric='first longitudinal frequency [Hz]', value=f, reference=f_ref,
    rel_error=(f - f_ref) / f_ref, seconds=r.run_s + r.compile_s,
    cells_across=h / grid.dx)


def timoshenko_cantilever_frequency(E, nu, rho, L, h, elements=400):
  """First bending frequency [Hz] of a clamped-free square Timoshenko beam.

  Finite elements with linear deflection and rotation and one-point shear
  integration (no locking), consistent mass including rotary inertia, shear
  coefficient 10 (1 + nu) / (12 + 11 nu) (Cowper, rectangular section).
  """
  from scipy.linalg import eigh
  G = E / (2 * (1 + nu))
  kap = 10 * (1 + nu) / (12 + 11 * nu)
  A, I = h * h, h ** 4 / 12
  n = elements
  l = L / n
  K = np.zeros((2 * n + 2, 2 * n + 2))
  M = np.zeros_like(K)
  b = np.array([-1 / l, -0.5, 1 / l, -0.5])
  kb = E * I / l * np.array([[0, 0, 0, 0], [0, 1, 0, -1], [0, 0, 0, 0],
                             [0, -1, 0, 1]])
  ks = kap * G * A * l * np.outer(b, b)
  mw = rho * A * l / 6 * np.array([[2, 1], [1, 2]])
  mt = rho * I * l / 6 * np.array([[2, 1], [1, 2]])
  for e in range(n):
    dofs = [2 * e, 2 * e + 1, 2 * e + 2, 2 * e + 3]
    K[np.ix_(dofs, dofs)] += kb + ks
    M[np.ix_(dofs[0::2], dofs[0::2])] += mw
    M[np.ix_(dofs[1::2], dofs[1::2])] += mt
  w2 = eigh(K[2:, 2:], M[2:, 2:], eigvals_only=True, subset_by_index=[0, 0])
  return float(np.sqrt(w2[0]) / (2 * math.pi))


def cantilever_mode(xi):
  """Euler-Bernoulli first clamped-free mode shape, xi = x / L (tip: 1)."""
  bl, sg = 1.8751, 0.7341

  def phi(s):
    s = np.clip(s, 0, None)
    return (np.cosh(bl * s) - np.cos(bl * s)
            - sg * (np.sinh(bl * s) - np.sin(bl * s)))
  return phi(xi) / phi(1.0)


def euler_bernoulli_frequency(E, rho, L, h):
  """First bending frequency [Hz] of a clamped-free square beam of side h."""
  return 1.8751 ** 2 / (2 * math.pi * L ** 2) * math.sqrt(E * h ** 2
                                                           / (12 * rho))


def crossing_frequency(t, y, level):
  """Frequency [Hz] from successive crossings of ``level`` by y(t)."""
  y = np.asarray(y) - level
  s = np.sign(y)
  idx = np.flatnonzero(s[:-1] * s[1:] < 0)
  tz = t[idx] - y[idx] * (t[idx + 1] - t[idx]) / (y[idx + 1] - y[idx])
  if len(tz) < 2:
    return float('nan')
  return 0.5 * (len(tz) - 1) / (tz[-1] - tz[0])


def cantilever(res, L=0.4, h=0.08, root=0.2, root_offset=0.0, periods=2.2,
               case='cantilever'):
  """First bending mode of a clamped cantilever (native API, no gravity).

  The clamp is a ``Cuboid`` holding the grid nodes at ``x <= root``; the
  beam starts 3 cells inside it. A grid clamp holds the beam at its last
  held node plane, so the root face is put on a node plane
  (``root_offset`` = 0); ``root_offset`` (cells, in [0, 1)) puts it that
  far past the node instead, which lengthens the free beam by as much.
  ``root`` [m] is rounded to a node.
  """
  grid = mpm.GridSpec(res=res, size=1.0)
  E, rho, nu = 1e5, 1000.0, 0.3
  root = (round(root / grid.dx) + root_offset) * grid.dx
  lo = np.array([root - 3 * grid.dx, 0.46, 0.46])
  x, vol = lattice(lo, np.array([root + L, lo[1] + h, lo[2] + h]),
                   grid.dx / 2)
  v = np.zeros_like(x)
  v[:, 2] = 0.05 * cantilever_mode((x[:, 0] - root) / L)
  mat = mpm.make_materials('fixed_corotated', E, nu, rho, num=len(x))
  f_ref = euler_bernoulli_frequency(E, rho, L, h)
  frame_dt = 1.0 / (f_ref * 40)
  n = mpm.choose_substeps(grid.dx, frame_dt, mat)
  # Clamp: grid nodes with x <= root are held at zero velocity.
  clamp = mpm.Cuboid(point=(root - 0.25, 0.5, 0.5),
                     size=(0.25 + 1e-3 * grid.dx, 0.5, 0.5))
  cfg = mpm.SimConfig(grid=grid, dt=frame_dt / n, substeps_per_frame=n,
                      gravity=(0, 0, 0), boundary_conditions=(clamp,))
  s = mpm.init_state(x, v, vol, mat, cfg)
  frames = int(periods / f_ref / frame_dt)
  tip = x[:, 0] > root + L - grid.dx / 2
  r = mpm.run(s, mat, None, cfg, frames)
  y = r.positions[:, tip, 2].mean(1)
  # Crossings of the rest position (no gravity), t = 0 excluded.
  f = crossing_frequency(r.times[1:], y[1:], y[0])
  f_timo = timoshenko_cantilever_frequency(E, nu, rho, L, h)
  return dict(
    case=case, res=res, particles=len(x), dt=cfg.dt,
    metric='first bending frequency [Hz]', value=f, reference=f_ref,
    rel_error=(f - f_ref) / f_ref, seconds=r.run_s + r.compile_s,
    cells_across=h / grid.dx, L_over_h=L / h, root_offset_cells=root_offset,
    tip_amplitude=float(np.ptp(y) / 2),
    timoshenko=f_timo, rel_error_timoshenko=(f - f_timo) / f_timo)


def cantilever_pg(res, L_over_h=10.0, h=0.140625, clamp_length=0.2,
                  E=3e7, rho=200.0, nu=0.3, periods=1.6,
                  exact_volumes=False):
  """First bending mode of a cantilever run through a PhysGaussian config.

  A beam of Gaussians on a lattice (2 per cell per axis on the ``res``^3
  grid, ``grid_lim`` 2: h = 0.140625 is 4.5 cells at 64^3) is normalised by
  ``physgaussian.prepare_config`` (``scale`` = its extent, so lengths are
  unchanged; centred at (1, 1, 1)), with occupancy volumes, gravity
  (0, 0, -9.8) and a zero-velocity ``cuboid`` clamp whose ``size`` is the
  half-extent (PhysGaussian tests ``|x - point| < size``) and whose face is
  on a node plane. It starts undeformed, so the tip oscillates about its
  sag; the frequency is from crossings of the midpoint of the tip's range
  after its first lowest point. ``exact_volumes``: give every particle the
  lattice cell volume instead of PhysGaussian's occupancy volume.
  """
  import jax.numpy as jnp
  from physsplat_jax import physgaussian as pgm
  from physsplat_jax.types import Gaussians
  lim = 2.0
  dx = lim / res
  L = L_over_h * h
  nh = int(round(h / (dx / 2)))
  sp = h / nh
  # Root face on a node plane: the beam is centred at x = 1 (a node).
  k = round((L - clamp_length) / (2 * dx))
  clamp_length = L - 2 * k * dx
  total = clamp_length + L
  x0 = 1.0 - total / 2
  root = x0 + clamp_length
  x, cell_vol = lattice((x0, 1 - h / 2, 1 - h / 2),
                        (x0 + total, 1 + h / 2, 1 + h / 2), sp)
  num = len(x)
  g = Gaussians(
    means=jnp.asarray(x - 1.0, jnp.float32),
    log_scales=jnp.full((num, 3), math.log(sp / 2), jnp.float32),
    quats=jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (num, 1)),
    opacity_logits=jnp.full((num,), 5.0), sh=jnp.zeros((num, 1, 3)))
  f_ref = euler_bernoulli_frequency(E, rho, L, h)
  frame_dt = 1.0 / (f_ref * 40)
  frames = int(periods / f_ref / frame_dt)
  raw = {
    'material': 'jelly', 'E': E, 'nu': nu, 'density': rho,
    'g': [0.0, 0.0, -9.8], 'n_grid': res, 'grid_lim': lim,
    'substep_dt': 1e-5, 'frame_dt': frame_dt, 'frame_num': frames,
    'scale': float(np.ptp(x, 0).max()), 'opacity_threshold': 0.02,
    'boundary_conditions': [
      {'type': 'bounding_box'},
      {'type': 'cuboid', 'point': [root / 2, 1.0, 1.0],
       'size': [root / 2 + 1e-3 * dx, 1.0, 1.0],
       'velocity': [0.0, 0.0, 0.0], 'start_time': 0.0, 'end_time': 1e3}]}
  prep = pgm.prepare_config(g, pgm.parse_config(raw, warn=False))
  xs = np.asarray(prep.state.x)
  assert np.abs(xs - x).max() < 1e-5 * lim, 'normalisation moved the beam'
  n = mpm.choose_substeps(prep.sim_config, frame_dt, prep.materials)
  sc = prep.sim_config.replace(dt=frame_dt / n, substeps_per_frame=n)
  state = prep.state
  if exact_volumes:
    state = mpm.init_state(xs, np.zeros(3), cell_vol, prep.materials, sc)
  r = mpm.run(state, prep.materials, prep.forces, sc, frames)
  tip = x[:, 0] > x[:, 0].max() - sp / 2
  y = r.positions[:, tip, 2].mean(1)
  # Swing about the sag: the midpoint of the range after the first lowest
  # point (a coarse beam loses part of its first swing).
  after = y[np.argmin(y[:len(y) // 2 + 1]):]
  mid = 0.5 * (after.max() + after.min())
  f = crossing_frequency(r.times, y, mid)
  f_timo = timoshenko_cantilever_frequency(E, nu, rho, L, h)
  tag = '_exact_vol' if exact_volumes else ''
  return dict(
    case=f'cantilever_pg_L{L_over_h:g}h{tag}', res=res, particles=num,
    dt=sc.dt,
    metric='first bending frequency [Hz]', value=f, reference=f_ref,
    rel_error=(f - f_ref) / f_ref, seconds=r.run_s + r.compile_s,
    cells_across=h / dx, L_over_h=L_over_h,
    sag=float(y[0] - mid),
    timoshenko=f_timo, rel_error_timoshenko=(f - f_timo) / f_timo)


def sand_slope(res, phi=30.0, radius=0.2, height=0.12):
  grid = mpm.GridSpec(res=res, size=1.0)
  floor = 0.1
  x, vol = lattice((0.5 - radius, 0.5 - radius, floor),
                   (0.5 + radius, 0.5 + radius, floor + height), grid.dx / 2)
  keep = np.hypot(x[:, 0] - 0.5, x[:, 1] - 0.5) < radius
  x = x[keep]
  mat = mpm.make_materials('drucker_prager', 3e5, 0.3, 2000.0, num=len(x),
                           friction_angle=phi)
  frame_dt, frames = 0.05, 16
  n = mpm.choose_substeps(grid.dx, frame_dt, mat, max_speed=3.0)
  cfg = mpm.SimConfig(
    grid=grid, dt=frame_dt / n, substeps_per_frame=n,
    models=('drucker_prager',),
    boundary_conditions=(mpm.SurfaceCollider(point=(0, 0, floor)),))
  s = mpm.init_state(x, np.zeros(3), vol, mat, cfg)
  r = mpm.run(s, mat, None, cfg, frames)
  xf = r.positions[-1]
  rr = np.hypot(xf[:, 0] - 0.5, xf[:, 1] - 0.5)
  # Height profile: the 95th percentile of z in radial bins; fit the flank
  # between 20% and 80% of the pile height.
  bins = np.arange(0, rr.max() + grid.dx, grid.dx)
  prof = []
  for a, b in zip(bins[:-1], bins[1:]):
    m = (rr >= a) & (rr < b)
    if m.sum() >= 5:
      prof.append((0.5 * (a + b), np.percentile(xf[m, 2], 95) - floor))
  prof = np.asarray(prof)
  hmax = prof[:, 1].max()
  sel = (prof[:, 1] > 0.2 * hmax) & (prof[:, 1] < 0.8 * hmax)
  slope = -np.polyfit(prof[sel, 0], prof[sel, 1], 1)[0] if sel.sum() >= 2 \
      else float('nan')
  angle = math.degrees(math.atan(slope))
  return dict(
    case=f'sand_slope_phi{phi:g}', res=res, particles=len(x), dt=cfg.dt,
    metric='flank slope angle [deg]', value=angle, reference=phi,
    rel_error=(angle - phi) / phi, seconds=r.run_s + r.compile_s,
    final_height=float(hmax), runout_radius=float(np.percentile(rr, 99)))


def pile_slope(xf, centre, floor, dx):
  """Flank angle [deg] and height of a conical pile of particles.

  The height profile is the 95th percentile of z in radial bins of one cell;
  a line is fitted to the flank between 20% and 80% of the pile height.
  """
  rr = np.hypot(xf[:, 0] - centre[0], xf[:, 1] - centre[1])
  bins = np.arange(0, rr.max() + dx, dx)
  prof = []
  for a, b in zip(bins[:-1], bins[1:]):
    m = (rr >= a) & (rr < b)
    if m.sum() >= 5:
      prof.append((0.5 * (a + b), np.percentile(xf[m, 2], 95) - floor))
  prof = np.asarray(prof)
  hmax = prof[:, 1].max()
  sel = (prof[:, 1] > 0.2 * hmax) & (prof[:, 1] < 0.8 * hmax)
  slope = -np.polyfit(prof[sel, 0], prof[sel, 1], 1)[0] if sel.sum() >= 2 \
      else float('nan')
  return math.degrees(math.atan(slope)), float(hmax), rr


def angle_of_repose(res, phi=30.0, volume_correction=1.0, radius=0.2,
                    height=0.45, damping=40.0, seconds=7.0):
  """Quasi-static angle of repose of a Drucker-Prager sand column.

  A quarter of a tall column (radius 0.2 m, height 0.45 m) stands in the
  corner of two frictionless 'slip' walls, which are exact symmetry planes
  of the full column, on a sticky floor. It collapses under a strong
  grid-velocity damping (``damping`` 1/s: terminal speed ``g / damping``,
  0.25 m/s), so it creeps into a cone without the momentum that makes a
  free collapse run out past the angle of repose; the flank angle of the
  pile at rest is compared with the friction angle.
  """
  grid = mpm.GridSpec(res=res, size=1.0)
  floor = 0.1
  wall = 0.1  # the corner (x, y) = (wall, wall)
  x, vol = lattice((wall, wall, floor),
                   (wall + radius, wall + radius, floor + height),
                   grid.dx / 2)
  x = x[np.hypot(x[:, 0] - wall, x[:, 1] - wall) < radius]
  mat = mpm.make_materials('drucker_prager', 3e5, 0.3, 2000.0, num=len(x),
                           friction_angle=phi,
                           dp_volume_correction=volume_correction)
  frame_dt = 0.05
  frames = int(round(seconds / frame_dt))
  n = mpm.choose_substeps(grid.dx, frame_dt, mat, max_speed=1.0)
  cfg = mpm.SimConfig(
    grid=grid, dt=frame_dt / n, substeps_per_frame=n,
    models=('drucker_prager',), velocity_damping=damping,
    boundary_conditions=(
      mpm.SurfaceCollider(point=(0, 0, floor)),
      mpm.SurfaceCollider(point=(wall, 0, 0), normal=(1, 0, 0),
                          surface='slip'),
      mpm.SurfaceCollider(point=(0, wall, 0), normal=(0, 1, 0),
                          surface='slip')))
  s = mpm.init_state(x, np.zeros(3), vol, mat, cfg)
  r = mpm.run(s, mat, None, cfg, frames)
  xf = r.positions[-1]
  angle, hmax, rr = pile_slope(xf, (wall, wall), floor, grid.dx)
  # Creep speed over the last frame.
  speed = float(np.abs(r.positions[-1] - r.positions[-2]).max() / frame_dt)
  tag = '' if volume_correction else '_novc'
  return dict(
    case=f'repose_phi{phi:g}{tag}', res=res, particles=len(x), dt=cfg.dt,
    metric='pile flank angle [deg]', value=angle, reference=phi,
    rel_error=(angle - phi) / phi, seconds=r.run_s + r.compile_s,
    final_height=hmax, runout_radius=float(np.percentile(rr, 99)),
    final_max_speed=speed)


def contact(res, ground=0.2537, seconds=1.0, surface='separate'):
  """Blocks of several materials and a rigid box resting on a fixed plane.

  The plane (``surface`` 'separate' with friction 0.5, or 'sticky') sits at
  an arbitrary height between grid nodes (0.2537 m). Each
  0.12 m block starts 0.02 m above it; after ``seconds`` the rest height of
  each block's underside (lowest particle minus half the lattice spacing)
  above the plane is reported in cells, with the largest penetration of any
  particle centre over the run and the change of the rigid box's pairwise
  distances.
  """
  from scipy.spatial.distance import pdist
  grid = mpm.GridSpec(res=res, size=1.0)
  sp = grid.dx / 2
  size = 0.12
  specs = [('jelly', 'fixed_corotated', 5e4, {}),
           ('metal', 'von_mises', 2e5, dict(yield_stress=2e3)),
           ('sand', 'drucker_prager', 2e5, dict(friction_angle=35.0)),
           ('rigid', 'rigid', 1e6, {})]
  xs, names, objs = [], [], []
  for k, (_, model, _, _) in enumerate(specs):
    corner = (0.2 + 0.16 * k, 0.44, ground + 0.02)
    x, vol = lattice(corner, np.add(corner, size), sp)
    xs.append(x)
    names += [model] * len(x)
    objs += [k] * len(x)
  x = np.concatenate(xs)
  objs = np.asarray(objs)
  models = tuple(m for _, m, _, _ in specs)
  E = np.asarray([specs[k][2] for k in objs])
  extra = {}
  for f in ('yield_stress', 'friction_angle'):
    vals = [sp_[3].get(f) for sp_ in specs]
    base = [mpm.model_default(m, f) for m in models]
    extra[f] = np.asarray([vals[k] if vals[k] is not None else base[k]
                           for k in objs])
  mat = mpm.make_materials(names, E, 0.3, 1000.0, config_models=models,
                           **extra)
  body = np.where(objs == 3, 0, -1)
  frame_dt = 0.02
  cfg = mpm.SimConfig(
    grid=grid, dt=1e-3, models=models, num_bodies=1,
    boundary_conditions=(mpm.SurfaceCollider(
      point=(0, 0, ground), surface=surface, friction=0.5),))
  n = mpm.choose_substeps(cfg, frame_dt, mat, body_id=body, max_speed=2.0)
  cfg = cfg.replace(dt=frame_dt / n, substeps_per_frame=n)
  s = mpm.init_state(x, np.zeros(3), vol, mat, cfg, body_id=body)
  r = mpm.run(s, mat, None, cfg, int(round(seconds / frame_dt)))
  xf = r.positions[-1]
  half = 0.5 * vol ** (1 / 3)  # half the lattice spacing
  rest, layer = {}, {}
  for k, (name, _, _, _) in enumerate(specs):
    z = xf[objs == k, 2]
    rest[name] = float((z.min() - half - ground) / grid.dx)
    # Compaction: particles within one lattice spacing of the plane at the
    # end over those in the bottom layer at the start (1: one layer).
    z0 = x[objs == k, 2]
    layer[name] = float(np.sum(z < ground + sp)
                        / np.sum(z0 < z0.min() + 0.5 * sp))
  pen = float(max(0.0, ground - r.positions[..., 2].min()) / grid.dx)
  drift = float(np.abs(pdist(xf[objs == 3]) - pdist(x[objs == 3])).max())
  worst = max(abs(v) for v in rest.values())
  return dict(
    case='contact' + ('' if surface == 'separate' else f'_{surface}'),
    res=res, particles=len(x), dt=cfg.dt,
    metric='max |rest height - plane| [cells]', value=worst,
    reference='0 (underside on the plane)', rel_error=0.0,
    seconds=r.run_s + r.compile_s, rest_cells=rest, floor_layer_ratio=layer,
    max_penetration_cells=pen, rigid_distance_change_m=drift)


def friction_angles(values) -> list[float]:
  """``--phis`` as angles in (0, 90) deg, or a usage error naming the flag
  (``--phis=abc`` was a ValueError traceback)."""
  try:
    phis = [float(v) for v in values]
  except ValueError:
    phis = []
  if not phis or not all(0.0 < p < 90.0 for p in phis):
    raise cli.usage_error(f'--phis={",".join(map(str, values))}: give '
                          'friction angles in (0, 90) deg separated by '
                          'commas, such as --phis=20,30,40')
  return phis


def main(argv):
  del argv
  quick = _QUICK.value
  phis = friction_angles(_PHIS.value)
  cli.check_output_file('out', _OUT.value)  # before the cases run
  plan = {
    'free_fall': [(free_fall, dict(res=r)) for r in ((16,) if quick
                                                     else (16, 32))],
    'bar_mode': [(bar_mode, dict(res=r)) for r in ((32,) if quick
                                                   else (32, 64))],
    'cantilever': [(cantilever, dict(res=r)) for r in ((32,) if quick
                                                       else (32, 64))],
    'cantilever_slender': [
      (cantilever, dict(res=r, L=0.7, h=0.07, root=0.15,
                        case='cantilever_slender'))
      for r in ((32,) if quick else (32, 64))],
    # 3 periods at 32^3: the slender beam (2.25 cells thick) is soft there.
    'cantilever_pg': [(cantilever_pg, dict(res=r, L_over_h=a,
                                           periods=3.0 if r < 64 else 1.6))
                      for r in ((32,) if quick else (32, 64))
                      for a in (5.0, 10.0)],
    'sand_slope': [(sand_slope, dict(res=r, phi=p))
                   for r in ((32,) if quick else (32, 48))
                   for p in (20.0, 35.0)],
    'contact': [(contact, dict(res=r, surface=f))
                for r in ((24,) if quick else (24, 40))
                for f in ('separate', 'sticky')],
    'repose': [(angle_of_repose, dict(res=r, phi=p,
                                      seconds=_REPOSE_SECONDS.value))
               for r in ((32,) if quick else (32, 48))
               for p in phis],
  }
  if not _CASES.value:
    raise cli.usage_error(f'--cases is empty: name one or more of '
                          f'{sorted(plan)}')
  if 'repose' in _CASES.value and not _REPOSE_SECONDS.value > 0:
    raise cli.usage_error(f'--repose_seconds={_REPOSE_SECONDS.value}: give '
                          'a simulated time > 0 [s] (default 7)')
  unknown = [c for c in _CASES.value if c not in plan]
  if unknown:
    raise cli.usage_error(f'--cases: unknown case(s) {unknown}; choose '
                          f'from {sorted(plan)}.')
  results = []
  for case in _CASES.value:
    for fn, kw in plan[case]:
      t0 = time.time()
      row = fn(**kw)
      row['wall_seconds'] = time.time() - t0
      logging.info('%s', row)
      print(json.dumps(row), flush=True)
      results.append(row)
  print('\n| case | grid | particles | dt [s] | value | reference | '
        'rel. error | wall [s] |')
  print('|---|---|---|---|---|---|---|---|')
  for r in results:
    ref = r['reference']
    ref = f'{ref:.4g}' if isinstance(ref, float) else ref
    print(f"| {r['case']} | {r['res']}^3 | {r['particles']} | {r['dt']:.3g} "
          f"| {r['value']:.4g} | {ref} | {100 * r['rel_error']:+.2f}% | "
          f"{r['wall_seconds']:.0f} |")
  if _OUT.value:
    cli.write_json(_OUT.value, results)


if __name__ == '__main__':
  cli.run(main)
