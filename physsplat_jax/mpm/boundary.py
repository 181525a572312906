"""Boundary conditions: grid-node constraints and particle velocity rules.

Grid conditions act on node velocities after the grid update (PhysGaussian's
``grid_postprocess``): the domain box (always on), ``SurfaceCollider`` and
``Cuboid``. Particle conditions act on particle velocities before P2G
(PhysGaussian's ``pre_p2g_operations`` and velocity modifiers):
``ParticleImpulse``, ``PointForce``, ``EnforceTranslation``,
``EnforceRotation`` and ``SequentialRelease``. Particle selections are made
once from the initial positions (``particle_bc_data``), as PhysGaussian's
selection kernels do.

Time windows are half-open, ``start <= t < end``, with ``t = k dt`` the time
at the start of substep ``k`` (compared with a half-substep margin so that
round-off in ``t`` never adds or drops a substep).

Enforced velocities (``EnforceTranslation``, ``EnforceRotation``,
``SequentialRelease``) also set the particles' affine matrix ``C`` to the
gradient of the prescribed velocity field (0, or ``-rotation_scale [n]_x``),
so that the prescribed rigid motion survives the APIC transfer exactly
(PhysGaussian sets only ``v``, which the transfer then smooths).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from physsplat_jax.mpm import base
from physsplat_jax.mpm import linalg as la

# Width of the domain-box border in cells (PhysGaussian's bounding_box
# padding).
BORDER = 3
# 'sticky' and 'separate' SurfaceCollider grid constraints act on nodes at
# least this many cells behind the plane (see ``particle_contact``).
CONTACT_NODE_DEPTH = 1.0
# A particle within this many cells of its contact distance touches a plane.
_TOUCH = 1e-3
# Surfaces whose grid velocity at the plane is constrained by node pairs.
_PAIRED = ('sticky', 'separate')
# A plane normal to a grid axis within this many cells of a node plane is
# put on it for the grid constraints (``plane_node_distance``). The
# pipeline places its ground on a node plane, to 0.1 um (prepare.py): up to
# 1e-5 cells off at dx = 5 mm.
_SNAP = 1e-4


def has_node_pairs(config: base.SimConfig) -> bool:
  """Whether a plane of ``config`` pairs nodes (``_plane_pairs``), so the
  substep needs the touching mass (a fifth P2G channel, in the eight of
  ``transfer.p2g``)."""
  return any(isinstance(bc, SurfaceCollider) and bc.surface in _PAIRED
             for bc in config.boundary_conditions)


def _active(t, start, end, dt):
  return (t >= start - 0.5 * dt) & (t < end - 0.5 * dt)


def particle_bc_data(config: base.SimConfig, x0) -> tuple:
  """Per-particle data of the particle boundary conditions.

  Args:
    config: static config.
    x0: (N, 3) initial positions [m].

  Returns:
    tuple of (N,) float arrays, one per ``config.particle_bcs`` entry: a 0/1
    mask, or for ``SequentialRelease`` the release time [s] (-inf: never
    held).
  """
  dtype = x0.dtype
  out = []
  for i in config.particle_bcs:
    bc = config.boundary_conditions[i]
    if isinstance(bc, (ParticleImpulse, EnforceTranslation)):
      if getattr(bc, 'point', None) is None:
        m = jnp.ones(x0.shape[:1], bool)
      else:
        m = jnp.all(jnp.abs(x0 - jnp.asarray(bc.point, dtype))
                    < jnp.asarray(bc.size, dtype), axis=-1)
    elif isinstance(bc, PointForce):
      r = x0 - jnp.asarray(bc.point, dtype)
      m = jnp.sum(r * r, -1) < bc.radius ** 2
    elif isinstance(bc, EnforceRotation):
      n = jnp.asarray(bc.normal, dtype)
      r = x0 - jnp.asarray(bc.point, dtype)
      h = r @ n
      rh = r - h[:, None] * n
      m = (jnp.abs(h) < bc.half_height) & (
        jnp.sum(rh * rh, -1) < bc.radius ** 2)
    elif isinstance(bc, SequentialRelease):
      L = bc.num_layers
      hl = abs(bc.start_position - bc.end_position) / L
      d = jnp.abs(x0[:, bc.axis] - bc.end_position)
      # Other axes: PhysGaussian's boxes span |x - 1| < 1 there.
      others = [a for a in range(3) if a != bc.axis]
      inside = jnp.all(jnp.abs(x0[:, others] - 1.0) < 1.0, axis=-1)
      held = inside & (d < L * hl) if hl > 0 else jnp.zeros_like(inside)
      layers = jnp.ceil(L - d / max(hl, 1e-30))
      t_rel = bc.end_time * layers / L
      out.append(jnp.where(held, t_rel, -jnp.inf).astype(dtype))
      continue
    else:  # pragma: no cover
      raise TypeError(type(bc))
    out.append(m.astype(dtype))
  return tuple(out)


ParticleImpulse = base.ParticleImpulse
PointForce = base.PointForce
EnforceTranslation = base.EnforceTranslation
EnforceRotation = base.EnforceRotation
SequentialRelease = base.SequentialRelease
SurfaceCollider = base.SurfaceCollider
Cuboid = base.Cuboid


def apply_particle_bcs(config: base.SimConfig, forces, bc_data, t, x, v, C,
                       mass, reduce_fn=None):
  """Particle velocity rules before P2G.

  Impulses and point forces act first, then the enforced velocities
  (translation, rotation, release) in list order, as PhysGaussian's
  ``p2g2p`` does: an enforced velocity is not changed by a force.

  Args:
    config: static config.
    forces: ``Forces``.
    bc_data: tuple from ``particle_bc_data`` (same particle order as x).
    t: () time [s].
    x, v: 3-tuples of (N,) positions [m] and velocities [m/s].
    C: nested-tuple affine matrices [1/s].
    mass: (N,) [kg].
    reduce_fn: sums a per-shard partial sum over all particles (None: the
      identity; ``lax.psum`` when the particles are split over devices).

  Returns:
    ``(v, C)``.
  """
  dt = config.dt
  v = list(v)
  C = [list(r) for r in C]

  def set_C(on, G):
    for a in range(3):
      for b in range(3):
        C[a][b] = jnp.where(on, G[a][b], C[a][b])

  # PhysGaussian's p2g2p runs every impulse (pre_p2g_operations) before any
  # velocity modifier (enforced translation, rotation, release), whatever
  # their order in the list: the forces first, then the overwrites.
  bcs = [(i, config.boundary_conditions[i], bc_data[k])
         for k, i in enumerate(config.particle_bcs)]
  bcs = ([e for e in bcs if isinstance(e[1], (ParticleImpulse, PointForce))]
         + [e for e in bcs
            if not isinstance(e[1], (ParticleImpulse, PointForce))])
  # A particle of volume 0 (init_state allows it) has no mass: a force per
  # particle moves it not at all instead of dividing by 0 (its NaN velocity
  # times its zero mass was NaN momentum on the grid). A select on the
  # input, so that the derivative is finite too.
  inv_mass = jnp.where(mass > 0, 1.0 / jnp.where(mass > 0, mass, 1.0), 0.0)
  for i, bc, data in bcs:
    val = forces.values[i]
    if isinstance(bc, ParticleImpulse):
      on = _active(t, bc.start_time, bc.start_time + bc.num_dt * dt, dt)
      s = jnp.where(on, dt, 0.0) * data * inv_mass
      v = [v[d] + s * val[d] for d in range(3)]
    elif isinstance(bc, PointForce):
      on = _active(t, bc.start_time, bc.end_time, dt)
      if bc.per_particle:
        s = jnp.where(on, dt, 0.0) * data * inv_mass
      else:
        total = jnp.sum(data * mass)
        if reduce_fn is not None:
          total = reduce_fn(total)
        # Safe division: an empty selection has total 0, and the derivative
        # of x / max(total, tiny) is x * inf * 0 = NaN there.
        s = jnp.where(on, dt, 0.0) * data / jnp.where(total > 0, total, 1.0)
      v = [v[d] + s * val[d] for d in range(3)]
    elif isinstance(bc, EnforceTranslation):
      on = _active(t, bc.start_time, bc.end_time, dt) & (data > 0.5)
      v = [jnp.where(on, val[d], v[d]) for d in range(3)]
      set_C(on, ((0.0,) * 3,) * 3)
    elif isinstance(bc, EnforceRotation):
      on = _active(t, bc.start_time, bc.end_time, dt) & (data > 0.5)
      n = bc.normal
      r = [x[d] - bc.point[d] for d in range(3)]
      h = r[0] * n[0] + r[1] * n[1] + r[2] * n[2]
      rh = [r[d] - h * n[d] for d in range(3)]
      cross = (rh[1] * n[2] - rh[2] * n[1], rh[2] * n[0] - rh[0] * n[2],
               rh[0] * n[1] - rh[1] * n[0])
      w = [val[0] * cross[d] + val[1] * n[d] for d in range(3)]
      v = [jnp.where(on, w[d], v[d]) for d in range(3)]
      # grad v = -rotation_scale [n]_x.
      s = val[0]
      set_C(on, ((0.0, s * n[2], -s * n[1]), (-s * n[2], 0.0, s * n[0]),
                 (s * n[1], -s * n[0], 0.0)))
    elif isinstance(bc, SequentialRelease):
      on = (t >= bc.start_time - 0.5 * dt) & (t < data - 0.5 * dt)
      v = [jnp.where(on, 0.0, v[d]) for d in range(3)]
      set_C(on, ((0.0,) * 3,) * 3)
  return tuple(v), tuple(tuple(r) for r in C)


def node_coords(grid: base.GridSpec, dtype):
  """Broadcastable node coordinates: (G,1,1), (1,G,1), (1,1,G) [m]."""
  G = grid.res
  i = jnp.arange(G, dtype=dtype) * grid.dx
  return (grid.lower[0] + i[:, None, None], grid.lower[1] + i[None, :, None],
          grid.lower[2] + i[None, None, :])


def _friction(v, vn, n, mu):
  """Coulomb friction on the tangential part after a contact.

  ``v`` is the velocity with the normal part already removed, ``vn < 0`` the
  removed approach speed; ``|v_t|`` shrinks by ``mu |vn|`` (not below 0).
  """
  if mu == 0:
    return v
  vt2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
  # |v_t| floored at sqrt(tiny) by a select, not jnp.maximum: a node at rest
  # on the collider has v_t = 0, and maximum's derivative multiplies the
  # (huge) derivative of sqrt there by 0; the select passes exact zeros.
  tiny = jnp.finfo(vt2.dtype).tiny
  vt = jnp.sqrt(jnp.where(vt2 > tiny, vt2, tiny))
  s = jnp.where(vn < 0, jnp.maximum(0.0, 1.0 + mu * vn / vt), 1.0)
  return [v[d] * s for d in range(3)]


def contact_planes(config: base.SimConfig, t):
  """Active ``SurfaceCollider`` planes as ``(point, normal, mu, surface, on)``.

  ``mu`` is ``inf`` for a sticky surface (no sliding); ``on`` is a ()
  bool.
  """
  out = []
  for bc in config.boundary_conditions:
    if isinstance(bc, SurfaceCollider):
      on = _active(t, bc.start_time, bc.end_time, config.dt)
      mu = math.inf if bc.surface == 'sticky' else float(bc.friction)
      out.append((bc.point, bc.normal, mu, bc.surface, on))
  return out


def particle_radius(vol0):
  """Half the side of a particle's cube of volume ``vol0`` [m]: its extent
  in front of a plane it rests on."""
  return 0.5 * jnp.cbrt(vol0)


def particle_contact(config: base.SimConfig, t, x, v, radius=0.0):
  """Surface colliders as particle constraints in G2P (deformable particles).

  A particle whose advected position ``x + dt v`` lies behind the plane
  (offset by its ``radius``)
  loses the approaching part of its normal velocity, down to the speed that
  brings it exactly onto the plane (``-max(d, 0) / dt``, ``d`` its signed
  distance), with Coulomb friction on the tangential part ('separate' and
  'slip'); on a 'sticky' plane every touching particle loses its tangential
  motion; particles already behind the plane are projected onto
  it. Together with ``apply_grid_bcs`` (which holds only nodes a cell or
  more behind the plane, so it cannot hold bodies above it; on a 'sticky'
  or 'separate' plane it also stops the grid velocity at the plane where
  particles touch it, ``_plane_pairs``) the support sits at the plane
  itself, wherever it lies between grid nodes.

  Args:
    config: static config.
    t: () time [s].
    x, v: 3-tuples of (N,) positions at the start of the substep [m] and G2P
      velocities [m/s].
    radius: (N,) or scalar particle extent [m] (``particle_radius``): the
      distance from the plane at which a particle touches it, so that the
      material's surface, not the particle centres, rests on the plane.

  Returns:
    ``(x_new, v_new)``: advected positions and constrained velocities.
  """
  dt = config.dt
  v = list(v)
  x_new = [x[d] + dt * v[d] for d in range(3)]
  for p, n, mu, surface, on in contact_planes(config, t):
    d0 = la.vdot([x[k] - p[k] for k in range(3)], n) - radius
    vn = la.vdot(v, n)
    target = -jnp.maximum(d0, 0.0) / dt
    hit = d0 + dt * vn < 0
    if surface == 'sticky':
      # Touching particles stick even when not pressed in this substep.
      hit = hit | (d0 <= _TOUCH * config.grid.dx)
    hit = on & hit
    dvn = jnp.where(hit, target - vn, 0.0)  # > 0 where hit
    w = la.add_scaled(v, -vn, n)
    if surface == 'sticky':
      w = [jnp.where(hit, 0.0, w[k]) for k in range(3)]
    else:
      w = _friction(w, -dvn, n, mu)
    w = la.add_scaled(w, vn + dvn, n)
    v = [jnp.where(hit, w[k], v[k]) for k in range(3)]
    x_new = [x[k] + dt * v[k] for k in range(3)]
    dn = la.vdot([x_new[k] - p[k] for k in range(3)], n) - radius
    push = jnp.where(on, jnp.maximum(-dn, 0.0), 0.0)
    x_new = la.add_scaled(x_new, push, n)
  return tuple(x_new), tuple(v)


def _axis_distances(grid: base.GridSpec, bc):
  """For a plane normal to grid axis ``k``: ``(k, d)``, the signed distances
  ``d`` (G,) [m] of the node layers along ``k`` (NumPy float64, the plane
  snapped as in ``plane_node_distance``); None for any other plane."""
  n = bc.normal
  axes = [d for d in range(3) if n[d] != 0.0]
  if len(axes) != 1:
    return None
  k = axes[0]
  c = (bc.point[k] - grid.lower[k]) / grid.dx
  if abs(c - round(c)) < _SNAP:
    c = float(round(c))
  return k, (np.arange(grid.res) - c) * grid.dx * n[k]  # n[k] = +-1


def plane_node_distance(grid: base.GridSpec, bc, dtype):
  """Signed distances of the grid nodes from the plane of ``bc`` [m]
  (broadcastable to (G, G, G); positive in front of it).

  For a plane normal to a grid axis the distances are exact multiples of
  ``dx`` from the plane's position in cells, which is put on the nearest
  node plane when within ``_SNAP`` cells of it. Otherwise a node on the
  plane, or one cell behind it, sat a round-off (~1e-18 m) off it: the
  node one cell behind was then paired (``_plane_pairs``) with a weight
  ``b ~ 1e-18`` instead of 0, and the round-off normal change it got made
  Coulomb friction stick its (zero) tangential velocity from rest, where
  any tangential perturbation slides: the gradient from rest was the
  stuck one (AD 0.24999 against differences 0.24852 in
  tests/grad_finite_test.py's slip-ground pipeline case).
  """
  axis = _axis_distances(grid, bc)
  if axis is not None:
    k, d = axis
    shape = [1, 1, 1]
    shape[k] = grid.res
    return jnp.asarray(d.reshape(shape), dtype)
  xs = node_coords(grid, dtype)
  return sum((xs[d] - bc.point[d]) * bc.normal[d] for d in range(3))


def plane_slab(grid: base.GridSpec, bc):
  """The node layers a plane's grid constraints can change, ``(k, lo,
  hi)``: layers ``lo <= i < hi`` along grid axis ``k``; None when the
  plane is not normal to a grid axis, or when the layers are most of the
  grid (then the whole grid is constrained).

  ``apply_grid_bcs`` changes only nodes behind the plane (``hit``) and the
  node pairs of ``_plane_pairs`` (a node less than a cell behind and its
  neighbour in front, less than a cell in front): every node less than a
  cell in front of the plane or behind it. The slab takes the layers less
  than 1.5 cells in front (a margin for round-off) and everything behind;
  it may be empty (``lo == hi``: the plane is behind the whole grid). A
  node's constraint reads only its neighbours along ``k`` inside the slab
  (a pair's two nodes are both in it), so constraining the slab alone
  gives the same velocities as the whole grid (tested bit for bit), for
  6 of the 32 layers of the demo's grid under its ground.
  """
  axis = _axis_distances(grid, bc)
  if axis is None:
    return None
  k, d = axis
  near = np.nonzero(d < 1.5 * grid.dx)[0]
  if near.size == 0:
    return k, 0, 0
  lo, hi = int(near.min()), int(near.max()) + 1
  if hi - lo > grid.res // 2:
    return None
  return k, lo, hi


def _shift(a, k: int, s: int):
  """``b[i] = a[i + s e_k]`` (``s = +-1``), zero past the grid edge."""
  sl = [slice(None)] * 3
  pad = [(0, 0)] * 3
  sl[k] = slice(1, None) if s > 0 else slice(None, -1)
  pad[k] = (0, 1) if s > 0 else (1, 0)
  return jnp.pad(a[tuple(sl)], pad)


def sticky_touch(config: base.SimConfig, t, x, radius):
  """(N,) 1 where a particle touches (or is behind) an active 'sticky' or
  'separate' plane (the node pairs of ``_plane_pairs``).

  The same distance test as ``particle_contact``'s (a particle at rest on
  a 'separate' plane touches it too).
  """
  out = jnp.zeros_like(x[0])
  for p, n, _, surface, on in contact_planes(config, t):
    if surface in _PAIRED:
      d0 = la.vdot([x[k] - p[k] for k in range(3)], n) - radius
      out = jnp.where(on & (d0 <= _TOUCH * config.grid.dx), 1.0, out)
  return out


@jax.custom_jvp
def node_velocity(p, m):
  """Grid-node velocity ``p / m`` (momentum over mass), 0 where ``m == 0``.

  The forward value is the plain quotient. Its derivative is written as
  ``(dp - v dm) / m``: JAX's own rule for ``1 / m`` multiplies by ``m^-2``,
  which overflows to inf in float32 for the tiny masses (< 1e-19 kg) that a
  node gets from particles at the very edge of their B-spline support (two
  axes with ``f - 0.5 ~ 1e-4`` are enough), and ``0 * inf`` then made the
  gradient NaN (issue 17: at 50k+ particles on the GPU). Nodes with
  ``0 < m <= tiny`` (subnormal) contribute no derivative: ``1 / m`` itself
  is not representable there.

  Args:
    p: (...) momentum component [kg m/s].
    m: (...) node mass [kg], >= 0.

  Returns:
    (...) velocity [m/s].
  """
  return p / jnp.where(m > 0, m, 1.0)


@node_velocity.defjvp
def _node_velocity_jvp(primals, tangents):
  p, m = primals
  dp, dm = tangents
  v = node_velocity(p, m)
  ok = m > jnp.finfo(m.dtype).tiny
  r = 1.0 / jnp.where(ok, m, 1.0)
  dv = jnp.where(ok, (dp - v * dm) * r, 0.0)
  return v, dv


def _plane_pairs(grid: base.GridSpec, bc, on, dist, mass, touch, gv):
  """The grid velocity at the plane itself, where material touches it.

  Each node less than a cell behind the plane (depth ``a``, measured along
  the normal; a cell is ``h = dx |n_k|`` along the normal's dominant axis
  ``k``) is paired with its neighbour in front (at ``b = h - a``) along
  that axis. Where particles touching the plane (``sticky_touch``) give
  either node mass (``touch`` > 0), the pair's velocities are projected,
  with the least change of kinetic energy (an impulse ``-(b, a) lam`` on
  the two masses), so that their linear interpolant at the plane,
  ``r = (b v_behind + a v_front) / h``, is zero ('sticky': every
  component) or does not approach it ('separate': the normal component
  ``r . n`` is raised to 0 where it is negative, an impulse along the
  normal, with Coulomb friction on each node's tangential velocity, which
  shrinks by ``friction`` times its normal change). Material stopped at
  the plane is then stopped in the velocity field too, so ``F`` records
  the compression of what presses on it. Pairs with no touching particle
  stay free, so approaching bodies are not slowed in front of the plane
  (they land on it, ``particle_contact``). With several such planes a
  particle touching any of them counts. ``dist`` is
  ``plane_node_distance``'s (a node on the plane has ``a = 0``, one a
  cell behind it ``b = 0``, exactly).
  """
  k = int(np.argmax(np.abs(bc.normal)))
  s = 1 if bc.normal[k] > 0 else -1
  h = grid.dx * abs(bc.normal[k])
  a = -dist
  b = h - a
  # Mass fractions q (behind) and 1 - q (front): the front node's change
  # depends on the momentum, not the velocity, of a light node behind (a
  # node at a stencil edge has a tiny mass and an ill-conditioned velocity).
  # (node_velocity is the safe quotient m1 / (m1 + m2) here.)
  q = node_velocity(mass, mass + _shift(mass, k, s))
  den = b * b * (1.0 - q) + a * a * q
  ok = (on & (a > 0) & (a <= h) & (den > 0)
        & (touch + _shift(touch, k, s) > 0))
  den = jnp.where(ok, den, 1.0)
  cb = jnp.where(ok, b * (1.0 - q) / den, 0.0)
  cf = jnp.where(ok, a * q / den, 0.0)
  if bc.surface == 'sticky':
    out = []
    for c in range(3):
      r = b * gv[c] + a * _shift(gv[c], k, s)
      out.append(gv[c] - r * cb - _shift(r * cf, k, -s))
    return out
  n = bc.normal
  vn = la.vdot(gv, n)
  r = jnp.minimum(b * vn + a * _shift(vn, k, s), 0.0)
  dv = r * cb + _shift(r * cf, k, -s)  # <= 0: minus the normal change
  w = _friction(la.add_scaled(gv, -vn, n), dv, n, bc.friction)
  return la.add_scaled(w, vn - dv, n)


def _surface_constraint(grid: base.GridSpec, bc, on, dist, gv, mass, touch):
  """A ``SurfaceCollider``'s grid constraint on node velocities ``gv``
  (3 arrays, the whole grid or a slab of it, ``dist`` the nodes' signed
  distances from the plane, broadcastable to them)."""
  n = bc.normal
  # 'sticky'/'separate': only nodes at least a cell behind the plane (a
  # node closer to it would hold particles up to 1.5 dx - depth in front
  # of it); the plane itself is enforced on particles
  # (``particle_contact``), and so is the grid velocity at the plane where
  # particles touch it (``_plane_pairs``). 'slip' is bilateral and keeps
  # every node behind the plane.
  depth = 0.0 if bc.surface == 'slip' else CONTACT_NODE_DEPTH * grid.dx
  hit = on & (dist < -depth)
  pairs = bc.surface in _PAIRED and mass is not None and touch is not None
  if bc.surface == 'sticky':
    gv = [jnp.where(hit, 0.0, gv[d]) for d in range(3)]
  else:
    vn = la.vdot(gv, n)
    if bc.surface == 'slip':
      rem = vn
    else:  # separate: only the approaching part
      rem = jnp.minimum(vn, 0.0)
    w = la.add_scaled(gv, -rem, n)
    w = _friction(w, vn, n, bc.friction)
    gv = [jnp.where(hit, w[d], gv[d]) for d in range(3)]
  if pairs:
    gv = _plane_pairs(grid, bc, on, dist, mass, touch, gv)
  return list(gv)


def apply_grid_bcs(config: base.SimConfig, forces, t, gv, mass=None,
                   touch=None):
  """Grid-node constraints after the grid update.

  Args:
    config: static config.
    forces: ``Forces``.
    t: () time [s].
    gv: 3-tuple of (G, G, G) node velocities [m/s].
    mass, touch: (G, G, G) node masses and masses of the particles touching
      a 'sticky' or 'separate' plane (``sticky_touch``) [kg]; None skips
      the node pairs at those planes (``_plane_pairs``).

  Returns:
    3-tuple of (G, G, G) node velocities.
  """
  grid = config.grid
  G = grid.res
  dt = config.dt
  gv = list(gv)
  xs = node_coords(grid, gv[0].dtype)
  for i, bc in enumerate(config.boundary_conditions):
    if isinstance(bc, SurfaceCollider):
      on = _active(t, bc.start_time, bc.end_time, dt)
      dist = plane_node_distance(grid, bc, gv[0].dtype)
      slab = plane_slab(grid, bc)
      if slab is None:
        gv = _surface_constraint(grid, bc, on, dist, gv, mass, touch)
        continue
      k, lo, hi = slab
      if lo == hi:
        continue  # the plane is behind every node
      # Only the slab of layers the plane can change (``plane_slab``).
      cut = lambda a: jax.lax.slice_in_dim(a, lo, hi, axis=k)  # noqa: E731
      part = _surface_constraint(
        grid, bc, on, cut(dist), [cut(a) for a in gv],
        None if mass is None else cut(mass),
        None if touch is None else cut(touch))
      gv = [jax.lax.dynamic_update_slice_in_dim(gv[d], part[d], lo, axis=k)
            for d in range(3)]
    elif isinstance(bc, Cuboid):
      vel = forces.values[i]
      on = _active(t, bc.start_time, bc.end_time, dt)
      moved = jnp.clip(t, bc.start_time, bc.end_time) - bc.start_time
      inside = None
      for d in range(3):
        c = bc.point[d] + moved * vel[d]
        m = jnp.abs(xs[d] - c) < bc.size[d]
        inside = m if inside is None else inside & m
      hit = on & inside
      gv = [jnp.where(hit, vel[d], gv[d]) for d in range(3)]
      if bc.reset:
        off = (~on) & (t < bc.end_time + 14.5 * dt)
        gv = [jnp.where(off, 0.0, gv[d]) for d in range(3)]
  # Domain box (always on): no velocity out of the 3-cell border.
  idx = jnp.arange(G)
  for d in range(3):
    shape = [1, 1, 1]
    shape[d] = G
    ii = idx.reshape(shape)
    out = ((ii < BORDER) & (gv[d] < 0)) | ((ii >= G - BORDER) & (gv[d] > 0))
    gv[d] = jnp.where(out, 0.0, gv[d])
  return tuple(gv)


def collider_summary(config: base.SimConfig) -> str:
  """One line per boundary condition, for logs."""
  lines = []
  for bc in config.boundary_conditions:
    lines.append(f'{type(bc).__name__}: ' + ', '.join(
      f'{k}={v}' for k, v in vars(bc).items()
      if not (isinstance(v, float) and math.isinf(v))))
  return '; '.join(lines) or 'domain box only'

