"""Rigid bodies inside MLS-MPM: velocity projection onto rigid motion.

After every G2P, the particles of body ``b`` (``body_id == b``) have their
velocities replaced by the body's rigid motion, with mass-weighted linear
and angular momentum conserved::

  M = sum m_p,  c = sum m_p x_p / M,  V = sum m_p v_p / M,
  L = sum m_p (r_p x v_p + dx^2/24 w_p),
  I = sum m_p (|r_p|^2 1 - r_p r_p^T) + M dx^2/24 1,
  omega = I^{-1} L,

(``r_p = x_p - c``, ``w_p`` the axial vector of the skew part of the G2P
affine velocity ``C_p``; the ``dx^2/24`` term is each particle's own
inertia as a cube of side dx/2, which keeps ``I`` invertible for a line or
a single particle, and its spin ``w_p`` is counted in ``L`` with the same
inertia, so that a free body keeps its angular velocity exactly).
Positions advance exactly, ``x_p = c + dt V + R(dt omega) r_p``, so pairwise
distances are preserved; the particles then get the rigid velocity at their
new positions, ``V + omega' x R(dt omega) r_p`` with ``C_p = [omega']_x`` and
``omega' = R I^{-1} R^T I omega`` (the angular momentum kept in the world
frame while the inertia turns with the body); and ``F_p <- R(dt omega) F_p``
(followed by one Newton orthonormalisation step) so that the particle
frames, and the Gaussians they carry, rotate with the body. Fixed bodies
have ``V = omega = 0``. Rigid particles carry no stress, so their stiffness
never limits the time step; they still take part in P2G, which couples them
two ways with the other materials.
Fixed planes (``SurfaceCollider``) and the domain walls act on a body as a
whole (``_plane_contacts``): a contact impulse and a translation out of the
plane, never a per-particle clamp.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from physsplat_jax import platforms
from physsplat_jax.mpm import linalg as la


# Up to this many segments (bodies + 1) the per-body sums are one dense
# product with the one-hot body matrix: a few fused kernels for all sums of a
# stage, deterministic on every backend. Above it, one segment_sum of the
# stacked columns.
_DENSE_SEGMENTS = 32


def _onehot_product(q, onehot):
  return jnp.dot(q.T, onehot, precision=jax.lax.Precision.HIGHEST)


def _onehot_reduction(q, onehot):
  return jnp.sum(q[:, :, None] * onehot[:, None, :], axis=0)


def _segment_sums(seg, num_segments, dtype, reduce_fn=None, form='auto',
                  last_empty=False):
  """``ssum(list of (N,) arrays) -> list of (num_segments,) sums``.

  All columns of one call are summed together (one (N, K) reduction instead
  of K scatters; the scatters dominated the substep of a scene with a rigid
  body on a CPU). ``reduce_fn`` (e.g. ``lax.psum``) is applied to the
  stacked partial sums. ``form`` (few segments only): 'product' (the
  columns times the one-hot body matrix, fastest on the CPU), 'reduction'
  (a masked sum, which XLA:GPU fuses with the columns' producers into one
  kernel, where the product is a GEMM launch of its own after a copy of
  its stacked operand) or 'auto' (the product on the CPU, the reduction
  elsewhere, chosen at lowering). ``last_empty`` (static): no particle is
  in the last segment (the solver's slice of rigid particles has no dump
  segment), whose sums are then zeros without being computed; with one
  segment left, 'reduction' is a plain column sum (on a GPU half the
  elements of the one-hot product's kernel, and no one-hot matrix) and
  'product' the product with a column of ones; 'auto' is then the column
  sum everywhere: from JAX 0.12 on, XLA:CPU rounds that matrix-vector
  product as one running sum (relative error 1.6e-6 on 1,570 rows against
  6e-8 for the column sum).
  """
  if last_empty:
    inner = _segment_sums(seg, num_segments - 1, dtype, None, form) if (
      num_segments > 2) else None

    def product(q):  # every particle in segment 0: (N, K) -> (K, 1)
      return _onehot_product(q, jnp.ones((q.shape[0], 1), dtype))

    def column(q):
      return jnp.sum(q, axis=0)[:, None]

    def one(q):
      if form in ('product', 'reduction'):
        return product(q) if form == 'product' else column(q)
      return column(q)

    def ssum_used(cols):
      out = (one(jnp.stack(cols, axis=1)) if inner is None
             else jnp.stack(inner(cols)))
      out = jnp.concatenate([out, jnp.zeros_like(out[:, :1])], axis=1)
      if reduce_fn is not None:
        out = reduce_fn(out)
      return list(out)

    return ssum_used
  if num_segments <= _DENSE_SEGMENTS:
    onehot = (seg[:, None] == jnp.arange(num_segments)).astype(dtype)

    def total(q):
      if form == 'product':
        return _onehot_product(q, onehot)
      if form == 'reduction':
        return _onehot_reduction(q, onehot)
      return platforms.platform_dependent(q, onehot, cpu=_onehot_product,
                                        default=_onehot_reduction)
  else:
    def total(q):
      return jax.ops.segment_sum(q, seg, num_segments=num_segments).T

  def ssum(cols):
    out = total(jnp.stack(cols, axis=1))  # (K, S)
    if reduce_fn is not None:
      out = reduce_fn(out)
    return list(out)

  return ssum


def _per_particle(seg, num_segments, dtype, form='auto'):
  """``at_all(list of (S,) per-segment arrays) -> list of (N,) arrays``,
  each particle's segment's value.

  ``form``: 'gather' (``a[seg]``), 'product' (few segments only: one
  product of the one-hot segment matrix with the stacked columns, exact:
  a sum of one value and zeros) or 'auto' (the product on the CPU, the
  gathers elsewhere, chosen at lowering). On the CPU, XLA fuses a per-body
  chain (the contact impulses, the rotation) into each gather and so
  recomputes it for every particle, once per column: twelve such gathers
  were ~4 % of the tabletop's substep. The product reads the columns
  once, computed.
  """
  def gather(*cols):
    # Unsigned indices: no wrapping of negative ones (a select over the
    # particles, on a GPU a kernel of its own).
    idx = seg.astype(jnp.uint32)
    return [a[idx] for a in cols]

  def product(*cols):
    onehot = (seg[:, None] == jnp.arange(num_segments)).astype(dtype)
    return list(jnp.dot(onehot, jnp.stack(cols, axis=1),
                        precision=jax.lax.Precision.HIGHEST).T)

  def at_all(cols):
    if form == 'gather' or num_segments > _DENSE_SEGMENTS:
      return gather(*cols)
    if form == 'product':
      return product(*cols)
    return platforms.platform_dependent(*cols, cpu=product, default=gather)

  return at_all


def _rodrigues(w):
  """Rotation matrices exp([w]_x) for a 3-tuple of (B,) rotation vectors."""
  th2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
  small = th2 < 1e-12
  th2s = jnp.where(small, 1.0, th2)
  th = jnp.sqrt(th2s)
  a = jnp.where(small, 1.0 - th2 / 6.0, jnp.sin(th) / th)
  b = jnp.where(small, 0.5 - th2 / 24.0, (1.0 - jnp.cos(th)) / th2s)
  K = la.skew_from(w)
  K2 = la.matmul(K, K)
  return la.add(la.eye(w[0]), la.add(la.scale(K, a), la.scale(K2, b)))


# Vectors below may mix arrays and Python floats (a plane's normal, static):
# terms with a Python zero are left out at trace time (``la.sum_products``),
# so the contact stage's program, one long per-body chain on a GPU, carries
# only the terms that are there.


def _cross(a, b):
  def det2(p, q, r, s):  # p q - r s
    if la.static_zero(r) or la.static_zero(s):
      return la.sum_products([(p, q)])
    if la.static_zero(p) or la.static_zero(q):
      return -(r * s)
    return p * q - r * s
  return (det2(a[1], b[2], a[2], b[1]), det2(a[2], b[0], a[0], b[2]),
          det2(a[0], b[1], a[1], b[0]))


def _inverse(A):
  """``A^{-1}`` of a symmetric invertible field (cofactors / det)."""
  c = la.cofactor(A)
  d = la.det(A)
  return tuple(tuple(c[i][j] / d for j in range(3)) for i in range(3))


def _apply(Ainv, b):
  """``Ainv b`` for a right-hand side with Python zeros."""
  return tuple(la.sum_products(zip(Ainv[i], b)) for i in range(3))


def anchor_indices(body_id, num_bodies):
  """Per segment (the B bodies, then the non-rigid particles), the index of
  one of its particles: a body's first (0 for a body with none), and 0 for
  the last. ``project`` takes each body's sums about its particle
  (``anchor_index``). Computed once per frame (the particles are reordered
  between frames), not per substep."""
  n = body_id.shape[0]
  seg = jnp.where(body_id >= 0, body_id, num_bodies)
  if num_bodies < _DENSE_SEGMENTS:  # argmax of no match is 0
    first = jnp.argmax(seg[:, None] == jnp.arange(num_bodies + 1), axis=0)
  else:  # segment_min of no particle is the int maximum
    first = jax.ops.segment_min(jnp.arange(n, dtype=jnp.int32), seg,
                                num_segments=num_bodies + 1)
    first = jnp.where(first < n, first, 0)
  return first.astype(jnp.int32).at[num_bodies].set(0)


def _anchor_points(anchor_index, body_id, x, reduce_fn):
  """Per segment (B+1,), the position (3-tuple) of its anchor particle;
  with ``reduce_fn`` (particles split over devices) the mean of every
  device's anchor (each device that holds particles of a body has one: a
  point inside the body, the same on all devices). Not differentiated: the
  projection does not depend on them (parallel axes)."""
  idx = anchor_index.astype(jnp.uint32)
  pts = [x[d][idx] for d in range(3)]
  if reduce_fn is not None:
    seg_ids = jnp.arange(idx.shape[0])
    has = ((body_id[idx] == seg_ids) & (seg_ids < idx.shape[0] - 1)).astype(
      pts[0].dtype)
    tot = reduce_fn(jnp.stack([has] + [has * p for p in pts]))
    count = jnp.where(tot[0] > 0, tot[0], 1.0)
    pts = [t / count for t in tot[1:]]
  return [jax.lax.stop_gradient(p) for p in pts]


def project(num_bodies, body_fixed, dx, dt, body_id, mass, x, v, F,
            reduce_fn=None, planes=(), contact_form='auto', C=None,
            origin=None, all_rigid=False, anchor_index=None):
  """Rigid-body projection of the G2P result.

  Args:
    num_bodies: static number of bodies B.
    body_fixed: static tuple of B bools.
    dx, dt: cell size [m] and substep [s].
    body_id: (N,) int32, -1 for non-rigid particles.
    mass: (N,) [kg].
    x: 3-tuple of (N,) positions at the start of the substep [m].
    v: 3-tuple of (N,) G2P velocities [m/s].
    F: nested-tuple deformation gradients.
    reduce_fn: sums per-body partial sums over all particles (None: the
      identity; ``lax.psum`` when the particles are split over devices).
    planes: contact planes ``(point, normal, mu, surface, on, radius)``
      (``boundary.contact_planes`` with the particles' extent ``radius``,
      (N,) or scalar [m], and the domain walls): see ``_plane_contacts``.
    contact_form: how the planes' contact sets are measured
      ('sequential', 'merged' or 'auto': by platform; ``_measure_contacts``).
    C: nested-tuple G2P affine velocities, whose spin (the axial vector of
      their skew part) enters ``L`` with each particle's own inertia, as it
      enters ``I``; None: no spin (particles given as points).
    origin: static 3-tuple [m] about which the per-body sums are taken in
      one pass and then moved to each body's centre (parallel axes) where
      no ``anchor_index`` is given; a point near the bodies keeps the
      float32 cancellation small. None: the coordinate origin.
    all_rigid: static: every particle given is rigid (``body_id >= 0``;
      the solver's slice of the rigid particles), so that no mask is
      computed.
    anchor_index: (B+1,) int, per body the index of one of its particles
      (``anchor_indices``), about which that body's sums are taken: the
      parallel-axis moves then cancel few digits in float32, wherever the
      body is. None: about ``origin``.

  Returns:
    ``(rigid, x_new, v_new, C_new, F_new)``: (N,) bool mask and the rigid
    values for every particle (meaningful where ``rigid``).
  """
  B = num_bodies
  if all_rigid:
    rigid, seg = jnp.ones(body_id.shape, bool), body_id
  else:
    rigid = body_id >= 0
    seg = jnp.where(rigid, body_id, B)
  dtype = mass.dtype

  ssum = _segment_sums(seg, B + 1, dtype, reduce_fn, last_empty=all_rigid)
  at_all = _per_particle(seg, B + 1, dtype)

  def at(a):  # per-body (B+1,) -> per-particle
    return at_all([a])[0]

  pairs = [(a, b) for a in range(3) for b in range(a, 3)]
  # Each particle's own spin: its inertia (m dx^2/24, as in I below) times
  # the axial vector of C's skew part (C = [omega]_x after a projection).
  # Without it, L missed what I counted and every projection slowed a free
  # body's spin (by ~8 % per substep for a body a few cells wide).
  spin = ([(dx * dx / 48.0) * mass * t for t in la.axial(C)]
          if C is not None else None)
  # All sums in one pass over the particles, about a point o of each body
  # (one of its particles, ``anchor_index``), moved to the mass centre by
  # the parallel-axis theorem: L_c = L_o - c' x P, S_c = S_o - M c' c'^T
  # (c' the centre about o). The sums about c itself need c first: a
  # second pass, on a GPU two more kernels per substep of a few us each.
  # About one fixed point for all (the grid's centre, before), far from a
  # small body, these moves cancelled most of the sums' digits: the
  # tabletop demo's can, 3 cm wide and 0.36 m from the grid's centre, came
  # out of one float32 projection 9.6e-5 m/s off float64 under JAX 0.12,
  # whose XLA:CPU rounds a matrix-vector product as one running sum (8e-7
  # under JAX 0.10); 1e-7 under both now. (Relative velocities, about an
  # anchor particle's, would cancel the momentum's few digits too, 5e-8,
  # but cost a GPU substep two kernels: the fusions around P2G changed.)
  if anchor_index is not None:
    o = _anchor_points(anchor_index, body_id, x, reduce_fn)
    q = [x[d] - od for d, od in enumerate(at_all(o))]
  else:
    o = (0.0, 0.0, 0.0) if origin is None else origin
    q = [x[d] - o[d] for d in range(3)]
  mq = [mass * q[d] for d in range(3)]
  mv = [mass * v[d] for d in range(3)]
  orbital = [mq[1] * v[2] - mq[2] * v[1], mq[2] * v[0] - mq[0] * v[2],
             mq[0] * v[1] - mq[1] * v[0]]
  if spin is not None:
    orbital = [a + b for a, b in zip(orbital, spin)]
  sums = ssum([mass] + mq + mv + orbital
              + [mq[a] * q[b] for a, b in pairs])
  M, Mq, P, Lo, So = sums[0], sums[1:4], sums[4:7], sums[7:10], sums[10:]
  # Safe division (an empty segment has M = 0): a select, so that the
  # derivative of 1 / M is never inf * 0.
  Ms = jnp.where(M > 0, M, 1.0)
  cq = [Mq[d] / Ms for d in range(3)]  # mass centre about origin
  c = [cq[d] + o[d] for d in range(3)]
  V = [P[d] / Ms for d in range(3)]
  r = [q[d] - cp for d, cp in enumerate(at_all(cq))]
  L = [Lo[0] - (cq[1] * P[2] - cq[2] * P[1]),
       Lo[1] - (cq[2] * P[0] - cq[0] * P[2]),
       Lo[2] - (cq[0] * P[1] - cq[1] * P[0])]
  # Second moments about c: S_ab = sum m r_a r_b.
  S = {(a, b): sa - M * cq[a] * cq[b] for (a, b), sa in zip(pairs, So)}
  r2 = S[0, 0] + S[1, 1] + S[2, 2]
  own = M * dx * dx / 24.0
  I = [[None] * 3 for _ in range(3)]
  for (a, b) in pairs:
    s_ab = -S[a, b]
    if a == b:
      s_ab = s_ab + r2 + own
    I[a][b] = I[b][a] = s_ab
  I = tuple(tuple(row) for row in I)
  # Empty (dump) segment: make I the identity so the solve stays finite.
  empty = M <= 0
  I = tuple(tuple(jnp.where(empty, float(a == b), I[a][b]) for b in range(3))
            for a in range(3))
  w = la.solve_sym(I, L)
  free = jnp.asarray([not f for f in body_fixed] + [False], dtype)
  V = [V[d] * free for d in range(3)]
  w = [w[d] * free for d in range(3)]

  def move(V, w, spin_after=False):
    # Every per-body value the particles need, in one ``at_all``.
    Rb = _rodrigues(tuple(dt * w[d] for d in range(3)))
    if spin_after:
      # The angular velocity after the rotation: the body's angular
      # momentum I w is kept in the world frame while its inertia turns
      # with it, I' = R I R^T, so w' = R I^-1 R^T I w (torque-free
      # precession; w' = w about a principal axis).
      Lw = tuple(la.sum_products((I[a][b], w[b]) for b in range(3))
                 for a in range(3))
      Lb = tuple(la.sum_products((Rb[b][a], Lw[b]) for b in range(3))
                 for a in range(3))
      y = la.solve_sym(I, Lb)
      w = [la.sum_products((Rb[a][b], y[b]) for b in range(3))
           for a in range(3)]
    cols = list(c) + list(V) + list(w) + [Rb[a][b] for a in range(3)
                                          for b in range(3)]
    got = at_all(cols)
    cp, Vp, wp = got[0:3], got[3:6], got[6:9]
    Rp = tuple(tuple(got[9 + 3 * a + b] for b in range(3)) for a in range(3))
    Rr = [Rp[d][0] * r[0] + Rp[d][1] * r[1] + Rp[d][2] * r[2]
          for d in range(3)]
    x_new = [cp[d] + dt * Vp[d] + Rr[d] for d in range(3)]
    return x_new, Vp, wp, Rp, Rr

  if planes:
    x_new, _, _, _, _ = move(V, w)
    # The moved positions, computed once per particle. Without the barrier
    # XLA:GPU fused their chain (the body's solve, its rotation) into the
    # contact sums' product, evaluated for every (particle, plane column,
    # segment): 22.3 of the tabletop substep's 69.5 us of device time on an
    # H200 (the can's 1,570 particles x 7 planes x 5 columns x 2 segments,
    # before the sums skipped the empty dump segment); with it, one kernel
    # more and the substep 0.076 -> 0.061 ms (docs/benchmarks.md). XLA:CPU
    # drops barriers before fusion: no change there.
    x_new = jax.lax.optimization_barrier(x_new)
    V, w, shift = _plane_contacts(planes, rigid, ssum, at, mass, r, x_new,
                                  V, w, I, M, free, contact_form)
    x_new, Vp, wp, Rp, Rr = move(V, w, spin_after=True)
    shifted = at_all(shift)
    x_new = [x_new[d] + shifted[d] for d in range(3)]
  else:
    x_new, Vp, wp, Rp, Rr = move(V, w, spin_after=True)
  x_new = tuple(x_new)
  # The rigid velocity field at the moved positions (``Rr``, consistent with
  # ``C = [w]_x`` there): with the unrotated ``r`` the particles' velocities
  # lagged their positions by the substep's rotation, so that every substep
  # removed part of the spin (a factor ~cos(dt |w|) of the orbital angular
  # momentum) and, on a body a few cells wide, drove a spurious precession.
  v_new = (Vp[0] + wp[1] * Rr[2] - wp[2] * Rr[1],
           Vp[1] + wp[2] * Rr[0] - wp[0] * Rr[2],
           Vp[2] + wp[0] * Rr[1] - wp[1] * Rr[0])
  C_new = la.skew_from(wp)
  Fr = la.matmul(Rp, F)
  # One Newton step F <- (F + F^{-T}) / 2 removes the round-off drift away
  # from a rotation (F starts as one).
  d = la.det(Fr)
  d = jnp.where(jnp.abs(d) < 1e-12, 1.0, d)
  Fr = la.scale(la.add(Fr, la.scale(la.cofactor(Fr), 1.0 / d)), 0.5)
  return rigid, x_new, v_new, C_new, Fr


def _plane_contacts(planes, rigid, ssum, at, mass, r, x_new, V, w, I, M,
                    free, form='auto'):
  """Rigid bodies against fixed planes: one contact impulse per body.

  For each plane, the particles of a body that would end the substep behind
  it are its contact set; at their mass centre ``r_c`` (relative to the
  body's centre) an impulse along the normal removes the approach speed
  ``u_n = (V + omega x r_c) . n < 0`` (plastic contact,
  ``j = -u_n / (1/M + (r_c x n) . I^-1 (r_c x n))``), and a tangential one
  removes the sliding speed up to the Coulomb bound ``mu j`` (all of it on a
  sticky plane). Afterwards the body is translated along the normal out of
  the plane by the mass-weighted mean penetration of its contact set (a
  sum, so particles may be split over devices; a flat face comes out at
  once, a curved one over a few substeps). Bodies stay exactly rigid, and
  rest on the plane instead of sinking as the grid-only coupling lets them
  (there the particles away from the bottom keep their full weight in the
  average).

  The contact sets are measured by ``_measure_contacts`` in one of two
  forms, chosen by platform at lowering: plane after plane, each after the
  shifts out of the earlier ones ('sequential', the CPU), or all at once
  from the unshifted positions in one per-body sum ('merged', elsewhere: 2
  kernels on a GPU, where a sum per plane takes 2 each, 14 for a ground
  and the six domain walls; on the CPU it was ~7 % slower per substep).
  The two agree exactly for orthogonal planes (the ground and the walls)
  and for a flat face on coincident ones, and to first order otherwise
  (any rest is removed in the next substeps). The impulses follow plane
  after plane. A frictionless plane (the domain walls, a 'slip' ground)
  has no tangential impulse (``mu jn = 0`` bounds it to exactly 0), so
  none is computed: the six walls' friction was ~1/3 of the largest
  kernel of a GPU substep and ~13 s of its compile time
  (docs/benchmarks.md).

  Returns:
    ``(V, omega, shift)``: per-body (B+1,) 3-tuples.
  """
  dtype = mass.dtype
  tiny = jnp.finfo(dtype).tiny
  # Divisions by a sum that may be 0 (an empty segment, an empty contact
  # set) divide by 1 there instead, by a select: the numerator is exactly 0
  # then, so the values are the same, and the derivative of the quotient
  # stays finite. Dividing by ``tiny`` gave cotangents of ~1/tiny = inf,
  # and 0 * inf = NaN in the per-body sums' backward pass.
  Ms = jnp.where(M > 0, M, 1.0)
  Iinv = _inverse(I)  # once, for every solve below

  def impulse(V, w, rc, dirn, j):
    # dirn: arrays, or a plane's normal as Python floats.
    V = [V[d] if la.static_zero(dirn[d]) else V[d] + free * j * dirn[d] / Ms
         for d in range(3)]
    dw = _apply(Iinv, _cross(rc, tuple(
      0.0 if la.static_zero(dirn[d]) else j * dirn[d] for d in range(3))))
    w = la.add_scaled(w, free, dw)
    return V, w

  def k_eff(rc, dirn):
    a = _cross(rc, dirn)
    return 1.0 / Ms + la.vdot(a, _apply(Iinv, a))

  measured = _measure_contacts(planes, rigid, ssum, at, mass, r, x_new, free,
                               form)
  shift = [jnp.zeros_like(M)] * 3
  for k, (_, n, mu, _, _, _) in enumerate(planes):
    mc, *mrc, dmax = measured[k]
    n_b = tuple(n)
    has = mc > 0
    mcs = jnp.where(has, mc, 1.0)
    rc = tuple(mrc[d] / mcs for d in range(3))
    u = [V[d] + c for d, c in enumerate(_cross(w, rc))]
    un = la.vdot(u, n_b)
    jn = jnp.where(has, jnp.maximum(-un, 0.0) / k_eff(rc, n_b), 0.0)
    V, w = impulse(V, w, rc, n_b, jn)
    shift = la.add_scaled(shift, dmax, n)
    if mu == 0.0:  # frictionless (the domain walls): no tangential impulse
      continue
    # Friction at the same point.
    u = [V[d] + c for d, c in enumerate(_cross(w, rc))]
    un = la.vdot(u, n_b)
    ut = [u[d] if la.static_zero(n[d]) else u[d] - un * n[d] for d in range(3)]
    ut2 = la.vdot(ut, ut)
    slides = ut2 > tiny  # else no tangent direction (and no friction)
    st = jnp.sqrt(jnp.where(slides, ut2, 1.0))
    t = tuple(jnp.where(slides, ut[d] / st, 0.0) for d in range(3))
    jt = jnp.where(slides, st / k_eff(rc, t), 0.0)
    if not mu == float('inf'):
      jt = jnp.minimum(jt, mu * jn)
    jt = jnp.where(has & slides, jt, 0.0)
    V, w = impulse(V, w, rc, t, -jt)
  return V, w, shift


def _measure_contacts(planes, rigid, ssum, at, mass, r, x_new, free,
                      form='auto'):
  """Per plane, the contact set's mass ``mc``, first moment ``m r_c`` and
  the shift ``dmax`` along the normal that takes the body out of it.

  ``dmax`` is the set's mass-weighted mean penetration (a sum, so the same
  with particles split over devices; any rest is removed in the next
  substeps). ``form``: 'sequential' (each plane measured after the shifts
  out of the earlier ones: a sum per plane), 'merged' (all from the
  unshifted positions in one sum; plane ``k``'s shift is its penetration
  less what the earlier shifts moved the body along ``n_k``, never back)
  or 'auto' (sequential on the CPU, merged elsewhere, chosen at lowering).

  Returns:
    per plane, ``[mc, mrc_x, mrc_y, mrc_z, dmax]`` of per-body (B+1,)
    arrays.
  """
  def columns(x, p, n, on, radius):
    dist = la.sum_products((x[d] - p[d], n[d]) for d in range(3)) - radius
    mh = jnp.where(rigid & on & (dist < 0), mass, 0.0)
    return ([mh] + [mh * r[d] for d in range(3)]
            + [mh * jnp.maximum(-dist, 0.0)])

  def depth(mc, mpen):
    return mpen / jnp.where(mc > 0, mc, 1.0) * free

  def sequential():
    x, out = list(x_new), []
    for p, n, _, _, on, radius in planes:
      mc, *mrc, mpen = ssum(columns(x, p, n, on, radius))
      dmax = depth(mc, mpen)
      x = la.add_scaled(x, at(dmax), n)
      out.append(jnp.stack([mc, *mrc, dmax]))
    return jnp.stack(out)

  def merged():
    sums = ssum(sum((columns(x_new, p, n, on, radius)
                     for p, n, _, _, on, radius in planes), []))
    shift, out = [0.0] * 3, []
    for k, (_, n, _, _, _, _) in enumerate(planes):
      mc, *mrc, mpen = sums[5 * k:5 * k + 5]
      done = la.sum_products(zip(shift, n))
      dmax = jnp.maximum(depth(mc, mpen) - done, 0.0)
      shift = la.add_scaled(shift, dmax, n)
      out.append(jnp.stack([mc, *mrc, dmax]))
    return jnp.stack(out)

  if form == 'sequential':
    table = sequential()
  elif form == 'merged':
    table = merged()
  elif form == 'auto':
    table = platforms.platform_dependent(cpu=sequential, default=merged)
  else:
    raise ValueError(f"_measure_contacts: form={form!r}; use 'sequential', "
                     "'merged' or 'auto'")
  return [list(row) for row in table]
