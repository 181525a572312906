"""Rigid bodies inside MLS-MPM: velocity projection onto rigid motion.

After every G2P, the particles of body ``b`` (``body_id == b``) have their
velocities replaced by the body's rigid motion, with mass-weighted linear
and angular momentum conserved::

  M = sum m_p,  c = sum m_p x_p / M,  V = sum m_p v_p / M,
  L = sum m_p r_p x v_p,  I = sum m_p (|r_p|^2 1 - r_p r_p^T) + M dx^2/24 1,
  omega = I^{-1} L,  v_p = V + omega x r_p,  C_p = [omega]_x,

(``r_p = x_p - c``; the ``dx^2/24`` term is each particle's own inertia as a
cube of side dx/2, which keeps ``I`` invertible for a line or a single
particle). Positions advance exactly, ``x_p = c + dt V + R(dt omega) r_p``,
so pairwise distances are preserved, and ``F_p <- R(dt omega) F_p`` (followed
by one Newton orthonormalisation step) so that the particle frames, and the
Gaussians they carry, rotate with the body. Fixed bodies have
``V = omega = 0``. Rigid particles carry no stress, so their stiffness never
limits the time step; they still take part in P2G, which couples them two
ways with the other materials.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from physsplat_jax.mpm import linalg as la


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


def project(num_bodies, body_fixed, dx, dt, body_id, mass, x, v, F,
            reduce_fn=None):
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

  Returns:
    ``(rigid, x_new, v_new, C_new, F_new)``: (N,) bool mask and the rigid
    values for every particle (meaningful where ``rigid``).
  """
  B = num_bodies
  rigid = body_id >= 0
  seg = jnp.where(rigid, body_id, B)
  dtype = mass.dtype

  def ssum(a):
    out = jax.ops.segment_sum(a, seg, num_segments=B + 1)
    return out if reduce_fn is None else reduce_fn(out)

  def at(a):  # per-body (B+1,) -> per-particle
    return a[seg]

  M = ssum(mass)
  # Safe division (an empty segment has M = 0): a select, so that the
  # derivative of 1 / M is never inf * 0.
  Ms = jnp.where(M > 0, M, 1.0)
  c = [ssum(mass * x[d]) / Ms for d in range(3)]
  V = [ssum(mass * v[d]) / Ms for d in range(3)]
  r = [x[d] - at(c[d]) for d in range(3)]
  mr = [mass * r[d] for d in range(3)]
  L = [ssum(mr[1] * v[2] - mr[2] * v[1]),
       ssum(mr[2] * v[0] - mr[0] * v[2]),
       ssum(mr[0] * v[1] - mr[1] * v[0])]
  r2 = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
  own = M * dx * dx / 24.0
  I = [[None] * 3 for _ in range(3)]
  for a in range(3):
    for b in range(a, 3):
      s = -ssum(mr[a] * r[b])
      if a == b:
        s = s + ssum(mass * r2) + own
      I[a][b] = I[b][a] = s
  I = tuple(tuple(row) for row in I)
  # Empty (dump) segment: make I the identity so the solve stays finite.
  empty = M <= 0
  I = tuple(tuple(jnp.where(empty, float(a == b), I[a][b]) for b in range(3))
            for a in range(3))
  w = la.solve_sym(I, L)
  free = jnp.asarray([not f for f in body_fixed] + [False], dtype)
  V = [V[d] * free for d in range(3)]
  w = [w[d] * free for d in range(3)]
  Rb = _rodrigues(tuple(dt * w[d] for d in range(3)))
  Vp = [at(V[d]) for d in range(3)]
  wp = [at(w[d]) for d in range(3)]
  Rp = tuple(tuple(at(Rb[a][b]) for b in range(3)) for a in range(3))
  v_new = (Vp[0] + wp[1] * r[2] - wp[2] * r[1],
           Vp[1] + wp[2] * r[0] - wp[0] * r[2],
           Vp[2] + wp[0] * r[1] - wp[1] * r[0])
  x_new = tuple(at(c[d]) + dt * Vp[d]
                + Rp[d][0] * r[0] + Rp[d][1] * r[1] + Rp[d][2] * r[2]
                for d in range(3))
  C_new = la.skew_from(wp)
  Fr = la.matmul(Rp, F)
  # One Newton step F <- (F + F^{-T}) / 2 removes the round-off drift away
  # from a rotation (F starts as one).
  d = la.det(Fr)
  d = jnp.where(jnp.abs(d) < 1e-12, 1.0, d)
  Fr = la.scale(la.add(Fr, la.scale(la.cofactor(Fr), 1.0 / d)), 0.5)
  return rigid, x_new, v_new, C_new, Fr
