"""Particle <-> grid transfers of MLS-MPM (Hu et al. 2018), structure of arrays.

Quadratic B-spline weights on the 3x3x3 stencil starting at
``base = floor(x / dx - 0.5)`` with ``f = x / dx - base``::

  w_0 = (1.5 - f)^2 / 2,  w_1 = 3/4 - (f - 1)^2,  w_2 = (f - 0.5)^2 / 2.

P2G scatters mass and APIC/MLS momentum with the stress folded into the
affine matrix (MLS-MPM)::

  m_i   += w_ip m_p
  (mv)_i += w_ip (m_p v_p + A_p (x_i - x_p)),
  A_p = m_p C_p - dt V_p^0 (4 / dx^2) tau_p.

G2P gathers ``v_p = sum_i w_ip v_i`` and
``C_p = (4 / dx^2) sum_i w_ip v_i (x_i - x_p)^T``.

Particles are fields of (N,) arrays (``x[d]``, ``A[d][e]``); the 27
neighbours are broadcast as (3, 3, 3, N) arrays and written with the offsets
``o in {0,1,2}^3`` as small integer multiples, since ``x_i - x_p = (o - f)
dx``. The grid is flat (``res^3`` nodes, z fastest).
"""

from __future__ import annotations

import itertools

import jax.numpy as jnp

from physsplat_jax.mpm.base import GridSpec

OFFSETS = tuple(itertools.product(range(3), repeat=3))


def _offset_axis(e: int, dtype):
  """Stencil offsets 0, 1, 2 along axis e, shaped to broadcast with (3,3,3,N)."""
  shape = [1, 1, 1, 1]
  shape[e] = 3
  return jnp.arange(3, dtype=dtype).reshape(shape)


class Stencil:
  """Weights and indices of the 3x3x3 stencil of every particle.

  Neighbour quantities are (3, 3, 3, N) arrays (offsets along x, y, z, then
  particles), built by broadcasting rather than gathering, which keeps the
  XLA program small (fast compiles) and vectorised.

  Attributes:
    f: 3-tuple of (N,) fractional positions ``x / dx - base`` in [0.5, 1.5).
    W: (3, 3, 3, N) weights ``w_x w_y w_z``.
    lin: (N,) int32 flat index of the base node.
  """

  def __init__(self, grid: GridSpec, x):
    inv_dx = grid.inv_dx
    xr = [(x[d] - grid.lower[d]) * inv_dx for d in range(3)]
    base = [jnp.floor(xr[d] - 0.5) for d in range(3)]
    self.f = tuple(xr[d] - base[d] for d in range(3))
    w = [jnp.stack([0.5 * (1.5 - f) ** 2, 0.75 - (f - 1.0) ** 2,
                    0.5 * (f - 0.5) ** 2]) for f in self.f]
    self.W = (w[0][:, None, None] * w[1][None, :, None]
              * w[2][None, None, :])
    b = [base[d].astype(jnp.int32) for d in range(3)]
    G = grid.res
    self.lin = (b[0] * G + b[1]) * G + b[2]
    self.res = G
    self.dtype = x[0].dtype

  def indices(self):
    """(27 N,) flat node indices, neighbour-major."""
    G = self.res
    i = jnp.arange(3, dtype=jnp.int32)
    off = (i[:, None, None] * (G * G) + i[None, :, None] * G
           + i[None, None, :])
    return (self.lin + off[..., None]).reshape(-1)


def p2g(grid: GridSpec, st: Stencil, v, mass, A):
  """Scatters mass and momentum to the grid.

  Args:
    grid: static grid.
    st: the particles' stencil.
    v: 3-tuple of (N,) velocities [m/s].
    mass: (N,) [kg].
    A: nested tuple affine matrix ``m C - dt V0 (4/dx^2) tau`` [kg/s].

  Returns:
    (res^3, 4) array: node mass [kg] and momentum (3) [kg m/s].
  """
  dx = grid.dx
  f = st.f
  o = [_offset_axis(e, st.dtype) for e in range(3)]
  # m v + A (o - f) dx = q + dx A o with q the part shared by all neighbours.
  cols = [st.W * mass]
  for d in range(3):
    q = mass * v[d] - dx * (A[d][0] * f[0] + A[d][1] * f[1] + A[d][2] * f[2])
    aff = o[0] * (dx * A[d][0]) + o[1] * (dx * A[d][1]) + o[2] * (
      dx * A[d][2])
    cols.append(st.W * (q + aff))
  vals = jnp.stack([c.reshape(-1) for c in cols], axis=-1)
  out = jnp.zeros((grid.num_nodes, 4), mass.dtype)
  return out.at[st.indices()].add(vals)


def g2p(grid: GridSpec, st: Stencil, gv):
  """Gathers particle velocities and affine matrices from the grid.

  Args:
    grid: static grid.
    st: the particles' stencil.
    gv: (res^3, 3) grid velocities [m/s].

  Returns:
    ``(v, C)``: 3-tuple of (N,) velocities and nested-tuple C [1/s].
  """
  shape = st.W.shape
  g = gv[st.indices()]                               # (27 N, 3)
  o = [_offset_axis(e, st.dtype) for e in range(3)]
  v, B = [], []
  for d in range(3):
    wg = st.W * g[:, d].reshape(shape)
    v.append(jnp.sum(wg, axis=(0, 1, 2)))
    B.append([jnp.sum(wg * o[e], axis=(0, 1, 2)) for e in range(3)])
  s = 4.0 * grid.inv_dx
  C = tuple(tuple(s * (B[d][e] - st.f[e] * v[d]) for e in range(3))
            for d in range(3))
  return tuple(v), C
