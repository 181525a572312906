"""Run a PhysGaussian ``config/*.json`` scene with the package MPM solver.

Follows PhysGaussian's ``gs_simulation.py`` (REFERENCE.md 1.1, 1.4):

1. drop Gaussians with activated opacity <= ``opacity_threshold``;
2. rotate (``rotation_degree`` / ``rotation_axis``) and keep those strictly
   inside ``sim_area``;
3. map into the normalised domain, a cube of side ``scale`` centred at
   (1, 1, 1) inside ``[0, grid_lim]^3`` (``physgaussian.schema``);
4. optionally fill the interior (``particle_filling``, with
   ``sampling.filling``; the filled particles are simulated but not output);
5. particle volumes from grid occupancy: ``dx^3 / (particles in the cell)``
   on the ``n_grid`` grid (their mean for sand, as PhysGaussian does);
6. simulate with the config's material, ``additional_material_params``,
   boundary conditions, gravity, damping and time step;
7. map the Gaussians' positions back to the input (PLY) frame.

``prepare_config`` does 1-6 and returns everything the solver needs (the
state, materials, forces and ``SimConfig``) so that a pipeline can also
differentiate or render; ``simulate_config`` runs it with ``mpm.run``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from absl import logging

from physsplat_jax import gaussians as gs
from physsplat_jax.physgaussian import schema as pg
from physsplat_jax.physgaussian import transform as pgt
from physsplat_jax.mpm import base
from physsplat_jax.mpm import solver
from physsplat_jax.mpm import timestep

ConfigError = pg.ConfigError


@dataclasses.dataclass
class PreparedSim:
  """A PhysGaussian scene ready for ``mpm.run`` / ``mpm.rollout``.

  Attributes:
    state: initial ``MPMState`` (normalised domain); the first
      ``num_gaussians`` particles are the selected Gaussians, in ``ids``
      order, the rest are fill particles.
    materials: per-particle ``Materials``.
    forces: ``Forces`` of the boundary conditions.
    sim_config: static ``SimConfig``.
    transform: ``NormTransform`` input frame -> normalised domain.
    ids: (num_gaussians,) row numbers of the simulated Gaussians in the input.
    num_gaussians: number of selected Gaussians.
    num_frames: ``frame_num`` of the config.
  """

  state: base.MPMState
  materials: base.Materials
  forces: base.Forces
  sim_config: base.SimConfig
  transform: pg.NormTransform
  ids: np.ndarray
  num_gaussians: int
  num_frames: int


def grid_volumes(x: np.ndarray, n_grid: int, grid_lim: float,
                 uniform: bool = False) -> np.ndarray:
  """PhysGaussian's particle volumes: cell volume / particles in the cell.

  Args:
    x: (N, 3) positions in ``[0, grid_lim]^3``.
    n_grid: cells per axis.
    grid_lim: domain side.
    uniform: give every particle the mean volume (PhysGaussian does so for
      sand).

  Returns:
    (N,) float64 volumes.
  """
  dx = grid_lim / n_grid
  cell = np.clip(np.floor(np.asarray(x, np.float64) / dx).astype(np.int64),
                 0, n_grid - 1)
  key = (cell[:, 0] * n_grid + cell[:, 1]) * n_grid + cell[:, 2]
  _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
  vol = dx ** 3 / counts[inv]
  if uniform:
    vol = np.full_like(vol, vol.mean())
  return vol


def _bc_time(bc, name, default):
  v = bc.get(name)
  return default if v is None else float(v)


def convert_boundary_conditions(config: pg.PhysGaussianConfig) -> tuple:
  """PhysGaussian ``boundary_conditions`` -> ``physsplat_jax.mpm`` dataclasses.

  ``bounding_box`` maps to the always-on domain box (nothing to add).

  Raises:
    ConfigError: a field the conversion needs is missing.
  """
  out = []
  src = config.source
  for i, bc in enumerate(config.boundary_conditions):
    where = f'{src}: boundary_conditions[{i}] ({bc.type})'
    t0 = _bc_time(bc, 'start_time', 0.0)
    t1 = _bc_time(bc, 'end_time', 1e3)
    if bc.type == 'bounding_box':
      continue
    if bc.type == 'cuboid':
      out.append(base.Cuboid(point=bc.get('point'), size=bc.get('size'),
                             velocity=bc.get('velocity'), start_time=t0,
                             end_time=t1, reset=bool(bc.get('reset', 0))))
    elif bc.type == 'particle_impulse':
      out.append(base.ParticleImpulse(
        force=bc.get('force'), num_dt=int(bc.get('num_dt', 1)),
        start_time=t0, point=bc.get('point', (1.0, 1.0, 1.0)),
        size=bc.get('size', (1.0, 1.0, 1.0))))
    elif bc.type == 'enforce_particle_translation':
      out.append(base.EnforceTranslation(
        point=bc.get('point'), size=bc.get('size'),
        velocity=bc.get('velocity'), start_time=t0, end_time=t1))
    elif bc.type == 'enforce_particle_velocity_rotation':
      hh, r = bc.get('half_height_and_radius')
      out.append(base.EnforceRotation(
        point=bc.get('point'), normal=bc.get('normal'), half_height=hh,
        radius=r, rotation_scale=float(bc.get('rotation_scale')),
        translation_scale=float(bc.get('translation_scale')),
        start_time=t0, end_time=t1))
    elif bc.type == 'surface_collider':
      surface = bc.get('surface')
      if surface == 'cut':
        logging.warning('%s: surface "cut" (a PhysGaussian special case with '
                        'hard-coded heights) is treated as "sticky".', where)
        surface = 'sticky'
      out.append(base.SurfaceCollider(
        point=bc.get('point'), normal=bc.get('normal'), surface=surface,
        friction=float(bc.get('friction', 0.0)), start_time=t0,
        end_time=t1))
    elif bc.type == 'release_particles_sequentially':
      axis = bc.get('axis')
      if axis is None:
        normal = bc.get('normal')
        if normal is None:
          raise ConfigError(f'{where}: give "normal" (e.g. [1, 0, 0]) or '
                            '"axis" (0, 1 or 2).')
        nz = [k for k, a in enumerate(normal) if a != 0]
        if len(nz) != 1:
          raise ConfigError(f'{where}: normal {normal} must have exactly one '
                            'non-zero component (an axis).')
        axis = nz[0]
      for f in ('start_position', 'end_position'):
        if bc.get(f) is None:
          raise ConfigError(f'{where}: missing field {f!r} (a coordinate '
                            'along the release axis, normalised units).')
      # PhysGaussian ignores num_layers and always uses 50.
      out.append(base.SequentialRelease(
        axis=int(axis), start_position=float(bc.get('start_position')),
        end_position=float(bc.get('end_position')), num_layers=50,
        start_time=t0, end_time=t1))
    else:  # pragma: no cover (the parser rejects unknown types)
      raise ConfigError(f'{where}: unsupported type.')
  return tuple(out)


def make_sim_config(config: pg.PhysGaussianConfig, **overrides
                    ) -> base.SimConfig:
  """The ``SimConfig`` of a PhysGaussian config (normalised domain).

  ``substeps_per_frame = round(frame_dt / substep_dt)`` (PhysGaussian's
  ``int()`` truncates, e.g. 399 instead of 400 for 0.04 / 1e-4).
  """
  kw = dict(
    grid=base.GridSpec(res=config.n_grid, lower=(0.0, 0.0, 0.0),
                       size=config.grid_lim),
    dt=config.substep_dt, substeps_per_frame=config.substeps_per_frame,
    num_frames=config.frame_num, gravity=config.g,
    models=(config.material,),
    boundary_conditions=convert_boundary_conditions(config),
    rpic_damping=config.rpic_damping,
    grid_v_damping_scale=config.grid_v_damping_scale,
    remat_frames=False, maxwell=config.mu_N > 0,
  )
  kw.update(overrides)
  return base.SimConfig(**kw)


def transform_host(config: pg.PhysGaussianConfig, means: np.ndarray):
  """``(R, centre, s)`` of ``make_norm_transform`` in float64 NumPy.

  Host-side twin used for the input <-> normalised maps of positions so
  that scenes with large coordinates keep full precision in float32 runs.
  """
  R = pgt.rotation_matrix(config)
  xr = np.asarray(means, np.float64) @ R.T
  lo, hi = xr.min(0), xr.max(0)
  return R, 0.5 * (lo + hi), config.scale / float(np.max(hi - lo))


def _normalise_host(th, x):
  R, c, s = th
  return (np.asarray(x, np.float64) @ R.T - c) * s + 1.0


def _denormalise_host(th, xn):
  R, c, s = th
  return ((np.asarray(xn, np.float64) - 1.0) / s + c) @ R


def _normalised_gaussians(gaussians, ids, config):
  """Means, log-scales and quaternions in the normalised domain (host)."""
  th = transform_host(config, np.asarray(gaussians.means)[ids])
  R, _, s = th
  means = _normalise_host(th, np.asarray(gaussians.means)[ids])
  log_scales = np.asarray(gaussians.log_scales, np.float64)[ids] + math.log(s)
  Rq = np.asarray(gs.quat_to_rotmat(jnp.asarray(gaussians.quats)[ids]),
                  np.float64)
  quats = np.asarray(gs.rotmat_to_quat(jnp.asarray(R @ Rq)), np.float64)
  return means, log_scales, quats


def fill_particles(config: pg.PhysGaussianConfig, gaussians, ids, transform,
                   key=None) -> np.ndarray:
  """Interior fill points (normalised domain) for ``particle_filling``.

  Maps PhysGaussian's block onto ``sampling.filling``: the fill grid spacing
  is ``grid_lim / particle_filling.n_grid`` (default ``4 n_grid``), or the
  longest side of ``boundary`` over it when given (as PhysGaussian),
  ``density_threshold``, ``max_partciels_per_cell`` [sic] and
  ``max_particles_num`` are used as is, ``boundary`` (a box in the
  normalised domain) restricts the fill; ``search_threshold``,
  ``search_exclude_direction``, ``ray_cast_direction``, ``smooth`` and
  ``visualize`` have no counterpart (a cell is interior when all 6 axis rays
  hit the shell).

  Returns:
    (M, 3) float64 points.
  """
  from physsplat_jax.sampling import filling

  pf = config.particle_filling
  del transform
  means, log_scales, quats = _normalised_gaussians(gaussians, ids, config)
  opac = np.asarray(jax.nn.sigmoid(jnp.asarray(gaussians.opacity_logits)),
                    np.float64)[ids]
  n_fill = int(pf.get('n_grid', 4 * config.n_grid))
  box = pf.get('boundary')
  # PhysGaussian's fill grid has n_grid cells over grid_lim, or over the
  # longest side of ``boundary`` when one is given (filling.py).
  side = (float(np.max(np.asarray(box[1::2], np.float64)
                       - np.asarray(box[0::2], np.float64)))
          if box is not None else config.grid_lim)
  spacing = side / n_fill
  ext = float(np.max(np.ptp(means, 0)))
  margin = 2
  res = int(np.clip(math.ceil(ext / spacing) + 2 * margin, 8, 256))
  fc = filling.FillConfig(
    grid_res=res, margin_cells=margin,
    density_threshold=float(pf.get('density_threshold', 5.0)),
    opacity_threshold=config.opacity_threshold,
    particles_per_cell=max(1, int(pf.get('max_partciels_per_cell', 1))),
    # PhysGaussian's semantics (density_threshold is opacity-weighted; axis
    # rays), not the flood fill make_candidates uses (docs/sampling.md).
    opacity_weighted=True, inside_test='rays', max_sigma_cells=2.0 / 3.0,
  )
  if key is None:
    key = jax.random.PRNGKey(0)
  res = filling.fill_gaussians_host(
    key, means, log_scales, quats, opac,
    max_particles=int(pf.get('max_particles_num', 2_000_000)), config=fc)
  pts = np.asarray(res.points, np.float64)
  if box is not None:
    b = np.asarray(box, np.float64)
    keep = np.all((pts >= b[0::2]) & (pts <= b[1::2]), axis=1)
    pts = pts[keep]
  if bool(res.overflow):
    logging.warning('%s: particle_filling hit max_particles_num = %s.',
                    config.source, pf.get('max_particles_num'))
  return pts


def prepare_config(gaussians, config: pg.PhysGaussianConfig,
                   dtype=jnp.float32, fill: bool = True,
                   key=None) -> PreparedSim:
  """Selects, normalises and sets up a PhysGaussian scene for simulation.

  Args:
    gaussians: input ``Gaussians`` (PLY frame).
    config: parsed PhysGaussian config (``physgaussian.schema``).
    dtype: float dtype of the simulation.
    fill: honour ``particle_filling`` (when present).
    key: PRNG key for the fill jitter.

  Returns:
    ``PreparedSim``.

  Raises:
    ConfigError: nothing selected, the object does not fit, bad BC fields.
  """
  means = np.asarray(gaussians.means, np.float64)
  opacity = np.asarray(jax.nn.sigmoid(jnp.asarray(
    gaussians.opacity_logits, jnp.float32)), np.float64)
  ids = pgt.select_particles(config, means, opacity)
  transform = pgt.make_norm_transform(config, means[ids], dtype=dtype)
  x = _normalise_host(transform_host(config, means[ids]), means[ids])
  num_g = len(ids)
  if fill and config.particle_filling is not None:
    extra = fill_particles(config, gaussians, ids, transform, key)
    logging.info('%s: particle_filling added %d interior particles.',
                 config.source, len(extra))
    x = np.concatenate([x, extra]) if len(extra) else x
  # Keep every particle's stencil inside the grid (PhysGaussian would crash).
  sc = make_sim_config(config, dtype='float64' if dtype == jnp.float64
                       else 'float32')
  lo, hi = sc.grid.particle_bounds
  if np.any((x < lo) | (x > hi)):
    raise ConfigError(
      f'{config.source}: particles leave the usable grid [{lo:.3g}, '
      f'{hi:.3g}]^3 after normalisation; lower "scale" or raise "grid_lim".')
  vol = grid_volumes(x, config.n_grid, config.grid_lim,
                     uniform=config.material == 'drucker_prager')
  xj = jnp.asarray(x, dtype)
  E, nu, rho = pgt.material_fields(config, xj)
  model = config.material
  extra_fields = dict(
    yield_stress=config.yield_stress, hardening=config.hardening,
    xi=config.xi, friction_angle=config.friction_angle,
    plastic_viscosity=config.plastic_viscosity, softening=config.softening,
  )
  extra_fields.update(config.maxwell_params)  # (Physics3D's branch)
  if model == 'snow' and config.xi == 0.0:
    # PhysGaussian's snow does nothing; ours needs Stomakhin's hardening
    # coefficient, so an unset xi takes its default 10.
    extra_fields['xi'] = base.MODEL_DEFAULTS['snow']['xi']
  if model in ('newtonian', 'bingham'):
    extra_fields['viscosity'] = (config.plastic_viscosity or
                                 base.MODEL_DEFAULTS[model]['viscosity'])
  if model == 'rigid':
    raise ConfigError(f'{config.source}: material "rigid" needs rigid bodies; '
                      'use the pipeline (physsplat_jax.pipeline) for them.')
  mat = base.make_materials(model, E, nu, rho, num=len(x), dtype=dtype,
                            **extra_fields)
  state = solver.init_state(xj, np.zeros(3), vol, mat, sc)
  return PreparedSim(
    state=state, materials=mat, forces=base.make_forces(sc, dtype),
    sim_config=sc, transform=transform, ids=ids, num_gaussians=num_g,
    num_frames=config.frame_num)


def simulate_config(
  gaussians, config: pg.PhysGaussianConfig, num_frames: int | None = None,
  auto_substeps: bool = False,
  on_frame: Callable[[int, np.ndarray], Any] | None = None,
  dtype=jnp.float32, fill: bool = True,
  on_frame_F: Callable[[int, np.ndarray, np.ndarray], Any] | None = None,
):
  """Simulates a PhysGaussian config and returns the Gaussians' trajectory.

  Args:
    gaussians: input ``Gaussians`` (PLY frame).
    config: parsed PhysGaussian config.
    num_frames: frames to simulate (default ``frame_num``).
    auto_substeps: if the config's ``substep_dt`` is unstable, pick a stable
      one (``mpm.choose_substeps``) instead of raising.
    on_frame: optional ``callback(frame, x)`` with the (num_gaussians, 3)
      float32 positions in the input frame, after every frame (frame 0 =
      initial).
    dtype: simulation float dtype.
    fill: honour ``particle_filling``.
    on_frame_F: optional ``callback(frame, x, F)`` with also the (K, 3, 3)
      deformation gradients of the simulated Gaussians in the input frame
      (``R^T F_n R``; the normalisation's scale cancels), for rendering
      ``Sigma' = F Sigma F^T`` as PhysGaussian does.

  Returns:
    ``(x, ids, t)``: x (T+1, K, 3) float32 positions of the simulated
    Gaussians in the input frame, ids (K,) their rows in the input, t (T+1,)
    times [s].

  Raises:
    ConfigError: bad config for this scene.
    SimulationError: unstable time step (unless ``auto_substeps``) or a
      blow-up, naming the frame and the fix.
  """
  prep = prepare_config(gaussians, config, dtype=dtype, fill=fill)
  sc = prep.sim_config
  try:
    timestep.check_dt(sc, prep.materials)
  except base.SimulationError as e:
    if not auto_substeps:
      raise base.SimulationError(
        f'{config.source}: {e} (or pass auto_substeps / --auto_substeps).',
        frame=None, reason='dt') from None
    n = timestep.choose_substeps(sc, config.frame_dt, prep.materials)
    logging.warning('%s: substep_dt %.3g s is unstable; using %d substeps '
                    'of %.3g s per frame.', config.source, sc.dt, n,
                    config.frame_dt / n)
    sc = sc.replace(dt=config.frame_dt / n, substeps_per_frame=n)
  frames = prep.num_frames if num_frames is None else num_frames
  k = prep.num_gaussians
  th = transform_host(config, np.asarray(gaussians.means)[prep.ids])

  def to_input(state):
    return _denormalise_host(th, np.asarray(state.x[:k])).astype(np.float32)

  traj = []

  R = th[0]

  def collect(f, state):
    x = to_input(state)
    traj.append(x)
    if on_frame is not None:
      on_frame(f, x)
    if on_frame_F is not None:
      Fn = np.asarray(state.F[:k], np.float64)
      on_frame_F(f, x, (R.T @ Fn @ R).astype(np.float32))

  logging.info('%s: %s, %d Gaussians + %d fill particles, grid %d^3, '
               'dt %.3g s x %d substeps/frame, %d frames.', config.source,
               config.material, k, prep.state.num - k, sc.grid.res, sc.dt,
               sc.substeps_per_frame, frames)
  # The next frame simulates while ``collect`` fetches, renders and queues
  # this one.
  try:
    res = solver.run(prep.state, prep.materials, prep.forces, sc, frames,
                     on_frame=collect, keep_positions=False, lookahead=True)
  except base.SimulationError as e:
    raise _json_fix(e, config, sc) from None
  t = np.arange(frames + 1) * sc.frame_dt
  del res
  return np.stack(traj), prep.ids, t


def _json_fix(e, config, sc):
  """The solver's blow-up with the fix in the JSON's terms (the solver
  speaks of dt and mpm.choose_substeps; this user sets substep_dt)."""
  head = solver.split_fix(e)
  if head is None:
    return e
  movers = sorted({b.type for b in config.boundary_conditions
                   if b.type in ('cuboid', 'particle_impulse',
                                 'enforce_particle_translation',
                                 'enforce_particle_velocity_rotation')})
  kicks = f', the {" / ".join(movers)} speeds or forces' if movers else ''
  return base.SimulationError(
    f'{config.source}: {head}Lower substep_dt in the JSON (now {sc.dt:.3g} '
    f's; --auto_substeps picks one stable at the start, not for speeds '
    f'gained later), lower E{kicks}, or raise grid_lim if it was thrown out '
    'of the grid.', e.frame, e.reason)
