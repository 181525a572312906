"""MLS-MPM time stepping: substep, frame, rollout and the host-loop run.

One substep (Hu et al. 2018, with PhysGaussian's ordering)::

  1. particle rules      impulses, point forces, enforced velocities
  2. constitutive update F_e, plastic state = return_map(F); tau(F_e)
  3. P2G                 mass, momentum with A = m C - dt V0 (4/dx^2) tau
  4. grid update         v = p / m + dt g, damping, boundary conditions
  5. G2P                 v, C from the grid; plane contact on particles;
                         rigid projection and contact; x += dt v,
                         F = (I + dt C) F_e; x clamped to the grid

The stress of step 2 reaches P2G as a materialised array (see
``constitute``); the public state keeps PhysGaussian's semantics (``F``
before its return mapping).

Inside a frame the state is held as structure of arrays (particle index
last; positions and velocities as one (6, N) array, ``Jp`` and ``ep`` as
one (2, N): on a GPU each is then written by one kernel per substep,
bitwise the same results on the CPU) and, with
``SimConfig.sort_particles``, permuted so that particles are sorted by grid
cell (gathers and the scatter then walk memory in order); the permutation
is undone at the end of the frame, so callers never see it.

``rollout`` is the differentiable path (nested ``lax.scan`` with
``jax.checkpoint`` per frame and per substep); ``run`` is the host loop with
progress logging, a stability check per frame and timing.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import Any, Callable, Iterator

import jax
import jax.numpy as jnp
import numpy as np
from absl import logging

from physsplat_jax import program_store
from physsplat_jax import sorting
from physsplat_jax import types
from physsplat_jax.mpm import base
from physsplat_jax.mpm import boundary
from physsplat_jax.mpm import constitutive
from physsplat_jax.mpm import graphs
from physsplat_jax.mpm import linalg as la
from physsplat_jax.mpm import inputs
from physsplat_jax.mpm import rigid as rigid_lib
from physsplat_jax.mpm import transfer
from physsplat_jax.mpm.base import MPMInputError
from physsplat_jax.mpm.health import FIX_START as FIX_START
from physsplat_jax.mpm.health import J_RANGE as J_RANGE
from physsplat_jax.mpm.health import MAX_F as MAX_F
from physsplat_jax.mpm.health import _stats
from physsplat_jax.mpm.health import check_state as check_state
from physsplat_jax.mpm.health import split_fix as split_fix
from physsplat_jax.types import Array


# ------------------------------------------------------------- grid nodes


# The grid velocity p / m with a derivative safe for tiny node masses
# (defined in boundary, which also uses it for mass fractions).
node_velocity = boundary.node_velocity


# ------------------------------------------------------------------- set-up


def _host(a):
  try:
    return np.asarray(a)
  except (jax.errors.TracerArrayConversionError,
          jax.errors.ConcretizationTypeError):
    return None


def init_state(x, v, volume, materials: base.Materials,
               config: base.SimConfig, body_id=None, F=None) -> base.MPMState:
  """Initial particle state.

  Args:
    x: (N, 3) positions [m], inside the grid.
    v: (N, 3) or (3,) initial velocities [m/s].
    volume: (N,) or scalar particle volumes [m^3].
    materials: ``Materials`` with (N,) leaves (``mass = rho * volume``).
    config: static config (grid, boundary conditions, bodies).
    body_id: (N,) int rigid body per particle (-1: not rigid) or None.
    F: optional (N, 3, 3) initial deformation gradients (default I).

  Returns:
    ``MPMState`` at t = 0. From host data (NumPy arrays, Python numbers)
    its arrays are built in NumPy and transferred, compiling nothing;
    given JAX arrays (or under a transformation) it works in jnp.

  Raises:
    MPMInputError (a ValueError): wrong shapes; particles outside the
      grid, negative or non-finite volumes, bad body ids or model ids
      (checked when the inputs are concrete).
  """
  dtype = jnp.dtype(config.jnp_dtype)
  # Host data (NumPy, Python; no JAX array among the particle inputs) is
  # built in NumPy and transferred at the end: in jnp each operation
  # compiled a program per particle count (9 with make_materials, 0.4 s
  # per new count on a 2-core CPU). JAX arrays and tracers stay in jnp.
  xp = np if all(types.is_host_data(a) for a in (x, v, volume, body_id, F)
                 if a is not None) else jnp
  x = xp.asarray(x, dtype)
  if x.ndim != 2 or x.shape[1] != 3:
    raise MPMInputError(f'init_state: x has shape {x.shape}; expected (N, 3) '
                        'positions.')
  n = x.shape[0]
  v = xp.asarray(v, dtype)
  if v.ndim <= 1:
    v = xp.broadcast_to(v, (n, 3))
  if v.shape != (n, 3):
    raise MPMInputError(f'init_state: v has shape {v.shape}; expected ({n}, 3) '
                        'or (3,).')
  volume = xp.asarray(volume, dtype)
  if volume.ndim > 1 or (volume.ndim == 1 and volume.shape not in ((n,),
                                                                  (1,))):
    raise MPMInputError(f'init_state: volume has shape {volume.shape}; '
                        f'expected ({n},) or a scalar [m^3].')
  volume = xp.broadcast_to(volume, (n,))
  # Zero is allowed: a massless particle follows the grid (a sampler may
  # leave a driver without candidates). Velocities: mpm.run checks them.
  vh = _host(volume)
  if vh is not None and n and not np.all(np.isfinite(vh) & (vh >= 0)):
    bad = ~(np.isfinite(vh) & (vh >= 0))
    i = int(np.argmax(bad))
    raise MPMInputError(
      f'init_state: volume is {float(vh[i]):.3g} for particle {i} '
      f'({int(bad.sum())} of {n} negative or not finite); give volumes >= 0 '
      '[m^3].')
  for f in base.FLOAT_FIELDS + ('model_id',):
    a = getattr(materials, f)
    if np.shape(a) != (n,):
      raise MPMInputError(
        f'init_state: materials.{f} has shape {np.shape(a)}; expected '
        f'({n},) (one value per particle; use make_materials).')
  if body_id is None:
    body_id = xp.full((n,), -1, np.int32)
  body_id = xp.asarray(body_id, np.int32)
  if body_id.shape != (n,):
    raise MPMInputError(f'init_state: body_id has shape {body_id.shape}; '
                        f'expected ({n},).')
  xh, bh, mh = _host(x), _host(body_id), _host(materials.model_id)
  if xh is not None and n:
    lo, hi = config.grid.particle_bounds
    rel = xh - np.asarray(config.grid.lower)
    bad = np.any((rel < lo) | (rel > hi), axis=1)
    if np.any(~np.isfinite(xh)):
      raise MPMInputError('init_state: x contains NaN/inf.')
    if np.any(bad):
      i = int(np.argmax(bad))
      raise MPMInputError(
        f'init_state: {int(bad.sum())} particles lie outside the simulation '
        f'grid (e.g. particle {i} at {xh[i].tolist()}; the usable domain is '
        f'[{np.add(config.grid.lower, lo).tolist()}, '
        f'{np.add(config.grid.lower, hi).tolist()}] m). Enlarge '
        'GridSpec.size, move GridSpec.lower, or rescale the scene.')
  if bh is not None and n:
    if bh.max() >= config.num_bodies or bh.min() < -1:
      raise MPMInputError(
        f'init_state: body_id values in [{bh.min()}, {bh.max()}] but '
        f'config.num_bodies = {config.num_bodies}; use -1 (not rigid) or '
        '0..num_bodies-1.')
  if mh is not None and n:
    if mh.min() < 0 or mh.max() >= len(config.models):
      raise MPMInputError(
        f'init_state: materials.model_id in [{mh.min()}, {mh.max()}] but '
        f'config.models has {len(config.models)} entries {config.models}.')
    if 'rigid' in config.models and bh is not None:
      rid = config.models.index('rigid')
      orphan = (mh == rid) & (bh < 0)
      if np.any(orphan):
        raise MPMInputError(
          f'init_state: {int(orphan.sum())} particles have model "rigid" but '
          'no body (body_id = -1); give each rigid object a body id and set '
          'SimConfig.num_bodies.')
    if config.model_counts is not None:
      counts = tuple(np.bincount(mh, minlength=len(config.models)).tolist())
      if counts != config.model_counts:
        raise MPMInputError(
          f'init_state: materials.model_id gives {counts} particles per '
          f'model of {config.models} but SimConfig.model_counts = '
          f'{config.model_counts}; set model_counts to those counts or None.')
      if bh is not None and np.any((bh >= 0) != (mh == config.models.index(
          'rigid') if 'rigid' in config.models else False)):
        raise MPMInputError(
          'init_state: with SimConfig.model_counts, the rigid particles '
          '(body_id >= 0) must be exactly those of model "rigid"; fix '
          'body_id/model_id or set model_counts=None.')
  eye = (xp.broadcast_to(xp.eye(3, dtype=dtype), (n, 3, 3))
         if F is None or config.maxwell else None)
  F = xp.asarray(eye if F is None else F, dtype)
  if F.shape != (n, 3, 3):
    raise MPMInputError(f'init_state: F has shape {F.shape}; expected '
                        f'({n}, 3, 3) deformation gradients.')
  if xp is np and types.in_host_memory(materials.rho):
    mass = np.asarray(materials.rho).astype(dtype) * volume
  else:
    mass = materials.rho.astype(dtype) * volume
  fields = dict(
    x=x, v=v, F=F, C=xp.zeros((n, 3, 3), dtype),
    Jp=xp.ones((n,), dtype), ep=xp.zeros((n,), dtype),
    vol0=volume, mass=mass, body_id=body_id,
    t=xp.zeros((), dtype), step=xp.zeros((), np.int32),
    F_N=eye if config.maxwell else None)
  if xp is np:  # (jnp.asarray of a NumPy array compiles per shape too)
    fields = {k: None if a is None else types.device_array(a)
              for k, a in fields.items()}
  return base.MPMState(
    bc_data=boundary.particle_bc_data(config, fields['x']), **fields)


# ------------------------------------------------------- SoA substep kernel


def _to_soa(state: base.MPMState):
  n = state.x.shape[0]
  carry = dict(
    xv=jnp.concatenate([state.x.T, state.v.T]),
    FC=jnp.concatenate([jnp.transpose(state.F, (1, 2, 0)).reshape(9, n),
                        jnp.transpose(state.C, (1, 2, 0)).reshape(9, n)]),
    Jpep=jnp.stack([state.Jp, state.ep]),
    t=state.t, step=state.step,
  )
  if state.F_N is not None:  # (SimConfig.maxwell)
    carry['FN'] = jnp.transpose(state.F_N, (1, 2, 0)).reshape(9, n)
  aux = dict(mass=state.mass, vol0=state.vol0, body_id=state.body_id,
             bc_data=state.bc_data)
  return carry, aux


def _from_soa(carry, aux) -> base.MPMState:
  return base.MPMState(
    x=carry['xv'][:3].T, v=carry['xv'][3:].T,
    F=jnp.transpose(carry['FC'][:9].reshape(3, 3, -1), (2, 0, 1)),
    C=jnp.transpose(carry['FC'][9:].reshape(3, 3, -1), (2, 0, 1)),
    Jp=carry['Jpep'][0],
    ep=carry['Jpep'][1],
    vol0=aux['vol0'], mass=aux['mass'], body_id=aux['body_id'],
    bc_data=aux['bc_data'], t=carry['t'], step=carry['step'],
    F_N=(jnp.transpose(carry['FN'].reshape(3, 3, -1), (2, 0, 1))
         if 'FN' in carry else None),
  )


def _step_time(step, dt: float, dtype):
  """The time [s] after ``step`` substeps of ``dt``, in ``dtype``."""
  return (step.astype(dtype) * dt).astype(dtype)


def _rigid_group(groups):
  """``(a, b)``: the rigid particles' slice of the grouped order, or None."""
  return ([(a, b) for m, a, b in groups if m == 'rigid'] or [None])[0]


def _with_anchors(config: base.SimConfig, aux):
  """``aux`` with each body's anchor particle (``rigid.anchor_indices``,
  indexed in the particles the projection gets: the rigid slice where the
  particles are grouped), once per call instead of once per substep."""
  if config.num_bodies == 0:
    return aux
  group = _rigid_group(constitutive.model_groups(config))
  body_id = aux['body_id']
  if group is not None:
    body_id = body_id[group[0]:group[1]]
  return dict(aux, body_anchor=rigid_lib.anchor_indices(body_id,
                                                        config.num_bodies))


def _make_soa_substep(config: base.SimConfig, reduce_fn=None):
  """``substep(carry, aux, materials, forces) -> carry`` on SoA fields.

  ``reduce_fn`` (None: identity) is applied to every sum over particles:
  the P2G grid, rigid-body momentum sums and total-force masses; with
  ``lax.psum`` the particles may be split over devices (docs/distributed.md).
  """
  red = (lambda a: a) if reduce_fn is None else reduce_fn  # noqa: E731
  grid = config.grid
  dt = config.dt
  inv_dx = grid.inv_dx
  lo, hi = grid.particle_bounds
  stress_scale = -dt * 4.0 * inv_dx * inv_dx
  rp = config.rpic_damping
  damp = 1.0
  if config.grid_v_damping_scale < 1.0:
    damp *= config.grid_v_damping_scale
  if config.velocity_damping > 0.0:
    damp *= float(np.exp(-config.velocity_damping * dt))
  g = config.gravity
  has_bodies = config.num_bodies > 0
  has_planes = any(isinstance(bc, base.SurfaceCollider)
                   for bc in config.boundary_conditions)
  has_sticky = boundary.has_node_pairs(config)  # sticky/separate planes
  # Domain walls for rigid bodies (moved out as a whole, not clamped per
  # particle, which would deform them).
  walls = []
  for d in range(3):
    e = tuple(float(k == d) for k in range(3))
    lo_p = tuple(grid.lower[k] + lo * e[k] for k in range(3))
    hi_p = tuple(grid.lower[k] + hi * e[k] for k in range(3))
    walls.append((lo_p, e, 0.0, 'separate', True, 0.0))
    walls.append((hi_p, tuple(-a for a in e), 0.0, 'separate', True, 0.0))

  groups = constitutive.model_groups(config)
  rigid_group = _rigid_group(groups)

  constitute = constitutive.make_update(config)

  def substep(c, aux, mat, forces):
    x = tuple(c['xv'][d] for d in range(3))
    v = tuple(c['xv'][3 + d] for d in range(3))
    FC = c['FC']
    C = la.rows_mat(FC, 9)
    t = c['t']
    mass, vol0 = aux['mass'], aux['vol0']
    with jax.named_scope('constitutive'):
      Fe, Jpep, tau = constitute(FC, c['Jpep'], aux['body_id'], mat)
      if config.maxwell:  # the solids' Maxwell branch, beside the update
        FN, tau_N = constitutive.maxwell_update(
          config.models, mat.model_id, la.rows_mat(c['FN'], 0), mat, dt,
          aux['body_id'] >= 0 if has_bodies else None, groups)
        FN, tau = transfer.materialize((FN, la.add(tau, tau_N)))

    with jax.named_scope('particle_bcs'):
      v, C = boundary.apply_particle_bcs(config, forces, aux['bc_data'], t, x,
                                         v, C, mass, reduce_fn)
    with jax.named_scope('p2g'):
      if rp > 0:
        C = la.sub(C, la.scale(la.add(C, la.transpose(C)), 0.5 * rp))
      k = stress_scale * vol0
      A = tuple(tuple(mass * C[i][j] + k * tau[i][j] for j in range(3))
                for i in range(3))
      st = transfer.Stencil(grid, x)
      radius = boundary.particle_radius(vol0) if has_planes else 0.0
      # Mass of the particles touching a sticky or separate plane
      # (``_plane_pairs``).
      touch = (mass * boundary.sticky_touch(config, t, x, radius)
               if has_sticky else None)
      gm = red(transfer.p2g(grid, st, v, mass, A, touch))
    with jax.named_scope('grid_update'):
      m = gm[..., 0]
      has = m > 0
      gv = tuple(jnp.where(has, node_velocity(gm[..., d + 1], m) + dt * g[d],
                           0.0)
                 for d in range(3))
      if damp != 1.0:
        gv = tuple(a * damp for a in gv)
      gv = boundary.apply_grid_bcs(config, forces, t, gv, m,
                                   gm[..., 4] if has_sticky else None)
      gv = tuple(a.reshape(-1) for a in gv)
    with jax.named_scope('g2p'):
      v_grid, C_new = transfer.g2p(grid, st, gv)
      if has_planes:
        x_new, v_new = boundary.particle_contact(config, t, x, v_grid,
                                                 radius)
      else:
        v_new = v_grid
        x_new = tuple(x[d] + dt * v_new[d] for d in range(3))
      F_new = la.add(Fe, la.scale(la.matmul(C_new, Fe), dt))
      if has_bodies:
        if rigid_group is not None:  # the rigid particles are [a, b)
          a, b = rigid_group
          take = lambda q: q[a:b]  # noqa: E731
          merge = lambda full, part: full.at[a:b].set(part)  # noqa: E731
        else:
          rb = aux['body_id'] >= 0
          take = lambda q: q  # noqa: E731
          merge = lambda full, part: jnp.where(rb, part, full)  # noqa: E731
        rad = take(radius) if jnp.ndim(radius) else radius
        _, xr, vr, Cr, Fr = rigid_lib.project(
          config.num_bodies, config.body_fixed, grid.dx, dt,
          take(aux['body_id']), take(mass), jax.tree.map(take, x),
          jax.tree.map(take, v_grid), jax.tree.map(take, Fe), reduce_fn,
          planes=[q + (rad,) for q in boundary.contact_planes(config, t)]
          + walls, C=jax.tree.map(take, C_new),
          all_rigid=rigid_group is not None,
          anchor_index=aux['body_anchor'])
        x_new = tuple(merge(p, q) for p, q in zip(x_new, xr))
        v_new = tuple(merge(p, q) for p, q in zip(v_new, vr))
        C_new = jax.tree.map(merge, C_new, Cr)
        F_new = jax.tree.map(merge, F_new, Fr)
      x_new = tuple(jnp.clip(x_new[d], grid.lower[d] + lo, grid.lower[d] + hi)
                    for d in range(3))
    step = c['step'] + 1
    out = dict(
      xv=jnp.stack(tuple(x_new) + tuple(v_new)),
      # F and C as one array: on a GPU one kernel writes both (two did).
      FC=jnp.stack(la.mat_rows(F_new) + la.mat_rows(C_new)), Jpep=Jpep,
      t=_step_time(step, dt, t.dtype), step=step,
    )
    if config.maxwell:  # F_N moves with the material as F does
      out['FN'] = jnp.stack(la.mat_rows(
        la.add(FN, la.scale(la.matmul(C_new, FN), dt))))
    return out

  return substep


def _check_inputs(state, materials, forces, config, values: bool = True):
  """Types and sizes of a step's inputs; returns ``forces`` (the defaults
  for None). With ``values``, concrete inputs (an eager ``rollout`` or
  ``substep_fn`` call) also get :func:`inputs.check_run_inputs`, as
  ``mpm.run`` does: a NaN velocity or ``nu = 0.5`` then fails with a
  message naming the field, not as NaN positions. Traced inputs (under
  ``jit``, ``grad``, ``vmap``) are not read."""
  if not isinstance(state, base.MPMState):
    raise TypeError('expected an MPMState (mpm.init_state) as the state.')
  if not isinstance(materials, base.Materials):
    raise TypeError('expected Materials (mpm.make_materials).')
  inputs.check_dtypes(state, materials, config.dtype)
  if (state.F_N is None) == config.maxwell:  # (static: safe under jit)
    raise MPMInputError(
      'the state ' + ('has no' if config.maxwell else 'carries a')
      + ' Maxwell branch (MPMState.F_N) but SimConfig.maxwell is '
      f'{config.maxwell}; build the state with mpm.init_state(..., config) '
      'of the config you run.')
  if forces is None:
    forces = base.make_forces(config, state.x.dtype)
  if len(forces.values) != len(config.boundary_conditions):
    raise MPMInputError(
      f'forces has {len(forces.values)} entries but the config has '
      f'{len(config.boundary_conditions)} boundary conditions; build it with '
      'mpm.make_forces(config).')
  if values and not any(isinstance(a, jax.core.Tracer)
                        for a in jax.tree.leaves((state, materials, forces))):
    inputs.check_run_inputs(state, materials, forces, config, caller='mpm')
  return forces


def make_substep(config: base.SimConfig) -> Callable:
  """Returns ``substep_fn(state, materials, forces) -> state`` (pure).

  The function converts to structure of arrays and back on every call; use
  ``make_frame`` for many substeps.
  """
  soa = _make_soa_substep(config)

  def substep_fn(state, materials, forces=None):
    forces = _check_inputs(state, materials, forces, config)
    if config.model_counts is not None:  # the model slices need the order
      state, materials, inv = _order(config, state, materials)
    else:
      inv = None
    carry, aux = _to_soa(state)
    out = soa(carry, _with_anchors(config, aux), materials, forces)
    return _unorder(_from_soa(out, aux), inv)

  return substep_fn


def _cell_key(grid: base.GridSpec, x):
  q = jnp.floor((x - jnp.asarray(grid.lower, x.dtype)) * grid.inv_dx)
  q = jnp.clip(q, 0, grid.res - 1).astype(jnp.int32)
  return (q[:, 0] * grid.res + q[:, 1]) * grid.res + q[:, 2]


def _permute(tree, perm):
  return jax.tree.map(lambda a: a[perm] if a.ndim and a.shape[0] ==
                      perm.shape[0] else a, tree)


def _order(config: base.SimConfig, state, materials):
  """Particles in the order the substep expects: by model (the slices of
  ``config.model_counts``), then by cell (``sort_particles``).

  Returns ``(state, materials, inv)``; ``inv`` (None: not permuted) undoes
  it (``_unorder``).
  """
  n = state.x.shape[0]
  grouped = config.model_counts is not None
  if grouped and sum(config.model_counts) != n:
    raise MPMInputError(
      f'SimConfig.model_counts = {config.model_counts} sums to '
      f'{sum(config.model_counts)} but there are {n} particles.')
  if not (config.sort_particles or grouped) or n <= 1:
    return state, materials, None
  cells = config.grid.res ** 3 if config.sort_particles else 1
  cell = (_cell_key(config.grid, jax.lax.stop_gradient(state.x))
          if config.sort_particles else jnp.zeros((n,), jnp.int32))
  # One unsigned key (model, then cell): a CUB radix sort on a GPU
  # (physsplat_jax/sorting.py); jnp.lexsort where it would not fit.
  if grouped and len(config.models) * cells >= 2 ** 32:
    perm = jnp.lexsort((cell, materials.model_id))
  else:
    key = cell.astype(jnp.uint32)
    if grouped:
      key = key + materials.model_id.astype(jnp.uint32) * jnp.uint32(cells)
    perm = sorting.argsort(key)
  return (_permute(state, perm), _permute(materials, perm),
          sorting.inverse_permutation(perm))


def _unorder(state, inv):
  return state if inv is None else _permute(state, inv)


def make_frame(config: base.SimConfig, reduce_fn=None) -> Callable:
  """Returns ``frame_fn(state, materials, forces) -> state``.

  A ``lax.scan`` over ``config.substeps_per_frame`` substeps. With
  ``config.remat_frames`` the frame is ``jax.checkpoint``-ed and so is each
  substep inside it, so the backward pass of a rollout stores one carry per
  frame plus, while a frame is replayed, one carry per substep.

  ``reduce_fn`` (default identity) sums partial particle sums across devices
  when the particles are sharded (``lax.psum`` inside ``shard_map``, see
  ``physsplat_jax.distributed.rollout_sharded``).
  """
  soa = _make_soa_substep(config, reduce_fn)
  n_sub = config.substeps_per_frame

  def frame_fn(state, materials, forces=None):
    forces = _check_inputs(state, materials, forces, config)
    state, materials, inv = _order(config, state, materials)
    carry, aux = _to_soa(state)
    # The time is not carried: each substep derives it from its step (as
    # the substep itself does for its output), so that no kernel of its own
    # updates it on a GPU; the first substep keeps the state's time.
    t0, step0 = carry.pop('t'), carry['step']
    aux_sub = _with_anchors(config, aux)

    def body(c, _):
      step = c['step']
      t = jnp.where(step == step0, t0, _step_time(step, config.dt, t0.dtype))
      out = soa(dict(c, t=t), aux_sub, materials, forces)
      del out['t']
      return out, None

    if config.remat_frames:
      body = jax.checkpoint(body)
    carry, _ = jax.lax.scan(body, carry, None, length=n_sub)
    t = _step_time(carry['step'], config.dt, t0.dtype)
    return _unorder(_from_soa(dict(carry, t=t), aux), inv)

  if config.remat_frames:
    return jax.checkpoint(frame_fn)
  return frame_fn


def rollout(state: base.MPMState, materials: base.Materials,
            forces: base.Forces | None, config: base.SimConfig,
            num_frames: int | None = None, reduce_fn=None):
  """Differentiable rollout over frames (``lax.scan``; jit-able).

  Args:
    state: initial state.
    materials: per-particle materials.
    forces: boundary-condition parameters (None: ``make_forces(config)``).
    config: static config.
    num_frames: frames T (default ``config.num_frames``).
    reduce_fn: sums over particles across devices (``make_frame``).

  Returns:
    ``(final_state, xs, Fs)``: xs (T+1, N, 3) positions [m] and Fs
    (T+1, N, 3, 3) deformation gradients, frame 0 the initial state.
  """
  num_frames = config.num_frames if num_frames is None else num_frames
  if num_frames is None or num_frames < 0:
    raise MPMInputError('rollout: pass num_frames (or set config.num_frames).')
  forces = _check_inputs(state, materials, forces, config)
  frame_fn = make_frame(config, reduce_fn)

  def body(s, _):
    s = frame_fn(s, materials, forces)
    return s, (s.x, s.F)

  final, (xs, Fs) = jax.lax.scan(body, state, None, length=num_frames)
  xs = jnp.concatenate([state.x[None], xs])
  Fs = jnp.concatenate([state.F[None], Fs])
  return final, xs, Fs


# ----------------------------------------------------------------- host loop


@dataclasses.dataclass
class RunResult:
  """Output of ``run``.

  Attributes:
    state: final ``MPMState``.
    positions: (T+1, N, 3) float32 host positions (None when not kept).
    times: (T+1,) frame times [s].
    frames: frames simulated.
    compile_s: seconds to compile the frame function (0 when a previous run
      with the same config and shapes already compiled it).
    run_s: seconds simulating (excluding compilation).
    substeps_per_s: particle-substeps per second over the run.
  """

  state: base.MPMState
  positions: np.ndarray | None
  times: np.ndarray
  frames: int
  compile_s: float
  run_s: float
  substeps_per_s: float


@functools.lru_cache(maxsize=32)
def _jitted(config: base.SimConfig):
  """Jitted frame and stats functions per (hashable) config, reused by run.

  A new ``jax.jit`` of a new closure would recompile on every ``run`` call;
  caching by config lets repeated runs (and same-shape scenes) reuse the
  compiled executables.
  """
  return jax.jit(make_frame(config)), functools.partial(_stats, config)


class FrameLoop:
  """The frame-by-frame host loop of :func:`run`, as an iterator.

  Compiles the frame once (cached by config and shapes), then yields
  ``(f, state)`` for ``f = 0 .. num_frames`` (frame 0 is the initial
  state), each frame checked for stability first. With ``lookahead`` the
  next frame is dispatched *before* frame ``f`` is yielded, so whatever the
  consumer does with frame ``f`` on the host (rendering, writing, checks)
  overlaps the device computing frame ``f + 1``; JAX's asynchronous
  dispatch does the rest. Device work the consumer dispatches for frame
  ``f`` then queues behind frame ``f + 1``; collect its results one
  iteration later to keep the device busy (``pipeline.run`` does). A frame
  that fails its check raises before it is yielded, and nothing after it
  is dispatched. A loop runs once: iterate a new one for a second run.

  Attributes:
    compile_s: seconds compiling (0 when an earlier loop compiled it).
    sim_s: seconds the host waited for simulated frames, dispatch
      included. Without lookahead this is the simulation's wall time, as
      :func:`run` reports it; with it, time the device spent while the
      consumer held control is not counted.
    frames: frames yielded after frame 0 so far.
    state: the last state yielded.
  """

  def __init__(self, state: base.MPMState, materials: base.Materials,
               forces: base.Forces | None, config: base.SimConfig,
               num_frames: int | None = None, *, check: bool = True,
               lookahead: bool = False, log_every: int = 1):
    num_frames = config.num_frames if num_frames is None else num_frames
    if num_frames is None:
      raise MPMInputError('run: pass num_frames (or set config.num_frames).')
    self.forces = _check_inputs(state, materials, forces, config,
                                values=False)
    if check:
      inputs.check_run_inputs(state, materials, self.forces, config)
    # The frame program depends on neither the frame count nor
    # rematerialisation (nothing is differentiated here): keyed without
    # them, a run of another length reuses the compiled frame.
    self.config = dataclasses.replace(config, num_frames=None,
                                      remat_frames=False)
    frame_jit, self._stats = _jitted(self.config)
    t0 = time.perf_counter()
    # Compiled once per config and argument shapes in a process
    # (program_store keeps them), traced once across processes when a
    # compilation cache is on.
    compiled = program_store.compile_stored(
      frame_jit, (state, materials, self.forces), name='mpm_frame',
      out_tree=jax.tree.structure(state), static_key=repr(self.config),
      compile_fn=lambda lowered: graphs.compile_frame(
        lowered, self.config.gpu_graphs))
    self._compiled = compiled
    self.compile_s = time.perf_counter() - t0
    self.state, self.materials = state, materials
    self.num_frames, self.check = num_frames, check
    self.lookahead, self.log_every = lookahead, log_every
    self.sim_s, self.frames = 0.0, 0
    self._started = False
    logging.info('mpm.run: %d particles, grid %d^3, dt %.3g s x %d '
                 'substeps per frame, %d frames; compiled in %.2f s',
                 state.num, self.config.grid.res, self.config.dt,
                 self.config.substeps_per_frame, num_frames, self.compile_s)

  @property
  def substeps_per_s(self) -> float:
    """Particle-substeps per second of ``sim_s`` so far."""
    total = self.state.num * self.config.substeps_per_frame * self.frames
    return total / max(self.sim_s, 1e-9)

  def _dispatch(self, state):
    t = time.perf_counter()
    nxt = self._compiled(state, self.materials, self.forces)
    stats = self._stats(nxt) if self.check else None
    self.sim_s += time.perf_counter() - t
    return nxt, stats

  def __iter__(self) -> Iterator[tuple[int, base.MPMState]]:
    if self._started:
      raise RuntimeError('FrameLoop runs once; make a new one to run again.')
    self._started = True
    config, n = self.config, self.num_frames
    state = self.state
    pending = self._dispatch(state) if self.lookahead and n > 0 else None
    yield 0, state
    for f in range(1, n + 1):
      if pending is None:
        pending = self._dispatch(state)
      t1 = time.perf_counter()
      state, stats = pending
      jax.block_until_ready(state.x)
      self.sim_s += time.perf_counter() - t1
      pending = None
      t = f * config.frame_dt
      if self.check:
        check_state(config, jax.device_get(stats), f, t)
      if self.lookahead and f < n:
        pending = self._dispatch(state)
      self.state, self.frames = state, f
      if f % self.log_every == 0 or f == n:
        logging.info('mpm.run: frame %d/%d t=%.4g s (%.3g '
                     'particle-substeps/s)', f, n, t, self.substeps_per_s)
      yield f, state


def run(state: base.MPMState, materials: base.Materials,
        forces: base.Forces | None, config: base.SimConfig,
        num_frames: int | None = None,
        on_frame: Callable[[int, base.MPMState], Any] | None = None,
        keep_positions: bool = True, check: bool = True,
        log_every: int = 1, lookahead: bool = False) -> RunResult:
  """Host loop: one jitted frame call per frame, with checks and progress.

  Each frame is waited for, checked, then handed to ``on_frame`` before the
  next one is dispatched, so ``run_s`` is the simulation's own time; with
  ``lookahead`` the next frame is dispatched first (:class:`FrameLoop`).

  Args:
    state: initial state.
    materials: per-particle materials.
    forces: boundary-condition parameters (None: defaults).
    config: static config.
    num_frames: frames (default ``config.num_frames``).
    on_frame: optional ``callback(frame_index, state)`` after every frame
      (frame 0 = initial state), e.g. to stream output to disk.
    keep_positions: collect the (T+1, N, 3) positions on the host.
    check: stability check per frame (NaN/inf, particles at the wall at
      speed, more than a cell per substep, |F| > 100, det F outside
      [0.01, 100]).
    log_every: log progress every this many frames.
    lookahead: dispatch frame ``f + 1`` before ``on_frame(f, ...)`` runs,
      so the callback's host work overlaps it; ``run_s`` is then the time
      spent waiting for frames.

  Returns:
    ``RunResult``.

  Raises:
    SimulationError: with the frame, the likely cause and the fix.
    MPMInputError: called inside ``jax.jit`` / ``grad`` / ``vmap`` (a host
      loop; :func:`rollout` is the traceable one), or bad inputs.
  """
  if any(isinstance(leaf, jax.core.Tracer)
         for leaf in jax.tree.leaves((state, materials, forces))):
    raise MPMInputError(
      'mpm.run is a host loop (it checks, logs and copies every frame to '
      'the host), so it cannot run under jax.jit, grad or vmap; call '
      'mpm.rollout there (pure, jittable and differentiable), or call '
      'mpm.run outside the transformation')
  loop = FrameLoop(state, materials, forces, config, num_frames,
                   check=check, lookahead=lookahead, log_every=log_every)
  positions = [] if keep_positions else None
  times = []
  for f, st in loop:
    if keep_positions:
      positions.append(np.asarray(st.x, np.float32))
    times.append(f * loop.config.frame_dt)
    if on_frame is not None:
      on_frame(f, st)
  return RunResult(
    state=loop.state,
    positions=np.stack(positions) if keep_positions else None,
    times=np.asarray(times), frames=loop.frames, compile_s=loop.compile_s,
    run_s=loop.sim_s, substeps_per_s=loop.substeps_per_s,
  )
