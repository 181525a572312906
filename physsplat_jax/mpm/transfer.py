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

Particles are fields of (N,) arrays (``x[d]``, ``A[d][e]``). Their 27
neighbours are handled particle-major, as (N, 27) weights and one windowed
scatter (P2G) or gather (G2P) of a 3 x 3 x 3 block of nodes per particle
on a (G, G, G, c) grid (z fastest), with the offsets ``o in {0,1,2}^3``
entering as small integer multiples since ``x_i - x_p = (o - f) dx``.
"""

from __future__ import annotations

import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np

from physsplat_jax import platforms
from physsplat_jax.mpm.base import GridSpec

OFFSETS = tuple(itertools.product(range(3), repeat=3))


_FORMS = ('auto', 'stack', 'select')


def _check_form(form: str) -> None:
  if form not in _FORMS:
    raise ValueError(f"form={form!r}; use 'auto', 'stack' or 'select'")


def _channels(cols, form: str = 'auto'):
  """(N, C) array whose column ``c`` is ``cols[c]`` ((N,) arrays or
  scalars).

  ``form``: 'stack' (a concatenation), 'select' (selects on a constant
  channel mask) or 'auto' (the stack on the CPU, the selects elsewhere,
  chosen at lowering). The values are the same; the programs are not.
  XLA:GPU emits a concatenation as a kernel of its own (an "input
  fusion"): at the paper's sizes each of P2G's per-particle channel blocks
  and the stencil's base indices became a kernel, where selects fuse into
  the kernels that use them. On the CPU the selects made the substep
  ~6-10 % slower (docs/benchmarks.md).
  """
  _check_form(form)
  shape = next(jnp.shape(a) for a in cols if jnp.ndim(a))
  cols = [jnp.broadcast_to(a, shape) for a in cols]

  def stack(*cols):
    return jnp.stack(cols, axis=-1)

  def select(*cols):
    ch = np.arange(len(cols))[None, :]
    out = cols[-1][:, None]
    for c in reversed(range(len(cols) - 1)):
      out = jnp.where(ch == c, cols[c][:, None], out)
    return jnp.broadcast_to(out, shape + (len(cols),))

  if form == 'stack':
    return stack(*cols)
  if form == 'select':
    return select(*cols)
  return platforms.platform_dependent(*cols, cpu=stack, default=select)


def _w1d(f):
  """The quadratic B-spline's three 1D weights at fractional positions
  ``f`` (offsets 0, 1, 2)."""
  return 0.5 * (1.5 - f) ** 2, 0.75 - (f - 1.0) ** 2, 0.5 * (f - 0.5) ** 2


def block_weights(f, form: str = 'auto'):
  """(N, 3, 3, 3) weights ``w_x w_y w_z`` of fractional positions ``f`` (a
  3-tuple of (N,) arrays), particle-major.

  ``form`` as in :func:`_channels`: each axis's three weights stacked,
  three (N, 3) arrays ('stack', the CPU's), or the three axes' weights as
  one (N, 3, 3) array of selects ('select', elsewhere: at the paper's
  sizes XLA:GPU made each of the three stacks a kernel of its own). The
  same values either way.
  """
  _check_form(form)

  def outer(w):
    return (w[0][:, :, None, None] * w[1][:, None, :, None]
            * w[2][:, None, None, :])

  def stack(*f):
    return outer([jnp.stack(_w1d(a), axis=-1) for a in f])      # 3 x (N, 3)

  def select(*f):
    fa = _channels(f, 'select')[:, :, None]                      # (N, 3, 1)
    o = np.arange(3).reshape(1, 1, 3)
    w0, w1, w2 = _w1d(fa)
    w = jnp.where(o == 0, w0, jnp.where(o == 1, w1, w2))         # (N, 3, 3)
    return outer([w[:, d] for d in range(3)])

  if form == 'stack':
    return stack(*f)
  if form == 'select':
    return select(*f)
  return platforms.platform_dependent(*f, cpu=stack, default=select)


def _offset_axis(e: int, dtype):
  """Stencil offsets 0, 1, 2 along axis e, to broadcast with (3, 3, 3, N)."""
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
    b = [base[d].astype(jnp.int32) for d in range(3)]
    self.base = tuple(b)
    G = grid.res
    self.lin = (b[0] * G + b[1]) * G + b[2]
    self.res = G
    self.dtype = x[0].dtype
    self._weights = None

  @property
  def W(self):
    """(3, 3, 3, N) weights ``w_x w_y w_z`` (offsets first)."""
    w = [jnp.stack(self.w1d(d)) for d in range(3)]
    return (w[0][:, None, None] * w[1][None, :, None]
            * w[2][None, None, :])

  def block_weights(self):
    """(N, 3, 3, 3) weights ``w_x w_y w_z``, particle-major
    (:func:`block_weights`; computed once per stencil: P2G and G2P share
    them)."""
    if self._weights is None:
      self._weights = block_weights(self.f)
    return self._weights

  def weights(self):
    """(N, 27) weights ``w_x w_y w_z``, particle-major, offsets in
    :data:`OFFSETS` order."""
    return self.block_weights().reshape(-1, 27)

  def w1d(self, d: int):
    """The three 1D weights along axis d, each (N,)."""
    return _w1d(self.f[d])

  def indices(self):
    """(27 N,) flat node indices, neighbour-major."""
    G = self.res
    i = jnp.arange(3, dtype=jnp.int32)
    off = (i[:, None, None] * (G * G) + i[None, :, None] * G
           + i[None, None, :])
    return (self.lin + off[..., None]).reshape(-1)


def _o4(dtype):
  """(27, 4) rows ``(1, o_x, o_y, o_z)`` of the stencil offsets."""
  return jnp.asarray(np.concatenate([np.ones((27, 1)),
                                     np.asarray(OFFSETS, float)], 1), dtype)


def materialize(a, like=None):
  """``a`` (an array or a pytree of arrays) itself, computed once into
  memory before its consumers.

  XLA:CPU fuses a cheap elementwise producer into each consumer, and into a
  gather it recomputes the producer for every gathered element: the grid
  update (division by the node mass, boundary conditions) was evaluated
  81 times per particle inside G2P's gather, which made G2P several times
  slower. ``optimization_barrier`` does not prevent it (XLA:CPU removes
  barriers before fusion), a conditional does: on the CPU ``a`` goes
  through a ``lax.cond`` whose branches both return it (its predicate,
  ``a`` has no NaN in its first entry, only picks which). Other platforms
  (where a conditional costs a host round trip and fusion is not the
  problem) get ``a`` unchanged, chosen by
  ``platforms.platform_dependent``. With ``like`` (a pytree of arrays) the
  predicate is taken from ``like`` instead: a tangent or cotangent ``a``
  then stays linear (JAX can transpose the conditional).
  """
  def on_cpu(a, like):
    first = jax.tree.leaves(like)[0].reshape(-1)[0]
    return jax.lax.cond(first == first, lambda b: b,
                        lambda b: jax.tree.map(lambda q: q + 0, b), a)
  like = a if like is None else like
  return platforms.platform_dependent(a, like, cpu=on_cpu,
                                      default=lambda b, _: b)


def _transpose_stop_gradient():
  """Gives JAX's ``stop_gradient`` a transpose (a zero cotangent) where it
  has none.

  Batched by ``jax.vmap`` (a batch of scenes), :func:`materialize`'s
  conditional becomes a select whose operands JAX passes through
  ``stop_gradient`` (the untaken branch). For the tangent that
  :func:`materialize_cotangent` materializes, that puts ``stop_gradient``
  on a linear value, and ``jax.grad`` of a vmapped rollout raised
  "Transpose rule ... for 'stop_gradient' not implemented" (the batch and
  particle-sharded gradients of MPDP training). The untaken branch's
  cotangent is zero, which is what the rule returns. (Internal JAX names:
  where they have moved, nothing is registered.)
  """
  try:
    from jax._src import ad_util  # noqa: PLC0415
    from jax._src.interpreters import ad  # noqa: PLC0415
    prim = ad_util.stop_gradient_p
  except (ImportError, AttributeError):
    return
  if prim not in ad.primitive_transposes:
    ad.primitive_transposes[prim] = lambda ct, x: [ad.Zero(x.aval)]


_transpose_stop_gradient()


@jax.custom_jvp
def materialize_cotangent(a):
  """``a`` itself; in the reverse pass its cotangent is computed once into
  memory (:func:`materialize`) before it flows on.

  Where ``a`` is sliced from a packed array (F and C from the carried
  ``FC``), the slices' transposes are pads summed into one loop fusion;
  XLA:CPU fused the whole stress VJP into it and evaluated it per row of
  the (18, N) result. The tangent goes through :func:`materialize`'s
  conditional (its predicate taken from ``a``), and the reverse pass, its
  transpose, through the same conditional: a custom JVP rather than a
  custom VJP, so that forward mode works too.
  """
  return a


@materialize_cotangent.defjvp
def _materialize_cotangent_jvp(primals, tangents):
  (a,), (t,) = primals, tangents
  return a, materialize(t, like=a)




def p2g(grid: GridSpec, st: Stencil, v, mass, A, extra=None):
  """Scatters mass and momentum to the grid.

  The 27 x 4 contributions ``w_k (m, q + dx A o_k)`` of a particle
  (``q = m v - dx A f``) are formed directly in the (N, 3, 3, 3, 4) layout
  of one ``scatter_add`` with a 3 x 3 x 3 x 4 window per particle on a
  (G, G, G, 4) grid, from (N, 4) per-particle terms ``(m, q)`` and
  ``(0, dx A[:, e])``. XLA:CPU canonicalises scatter updates to
  particle-major order anyway; building them in that order with few
  operations per element avoids a transposed copy of the 108 N
  contributions, which dominated a structure-of-arrays formulation.

  Args:
    grid: static grid.
    st: the particles' stencil.
    v: 3-tuple of (N,) velocities [m/s].
    mass: (N,) [kg].
    A: nested tuple affine matrix ``m C - dt V0 (4/dx^2) tau`` [kg/s].
    extra: optional (N,) per-particle quantity scattered with the weights
      as a fifth channel (e.g. the mass of particles touching a plane).

  Returns:
    (G, G, G, 4) array (5 with ``extra``): node mass [kg], momentum (3)
    [kg m/s] and the scattered ``extra``.
  """
  dx = grid.dx
  f = st.f
  z = jnp.zeros_like(mass)
  # m v + A (o - f) dx = q + dx A o with q the part shared by all neighbours.
  q = [mass * v[d] - dx * (A[d][0] * f[0] + A[d][1] * f[1] + A[d][2] * f[2])
       for d in range(3)]
  col = lambda a: a[:, None, None, None, :]  # noqa: E731
  # With ``extra``, eight channels (three of zeros): XLA:CPU does not
  # vectorise a five-channel window (P2G 0.71 -> 2.4 ms at 6,000 particles
  # on 32^3), and a second, one-channel scatter costs as much as the first
  # inside the substep; eight take 1.15 ms (the demo scene resting on a
  # paired plane: 4.29 ms per substep, against 6.69 with five channels,
  # 5.00 with two scatters and 4.01 without the channel).
  tail = [] if extra is None else [extra] + [z] * 3
  Q = col(_channels([mass] + q + tail))
  Ae = [col(_channels([z] + [dx * A[d][e] for d in range(3)]
                      + [z] * len(tail)))
        for e in range(3)]
  W = st.block_weights()                                      # (N, 3, 3, 3)
  out = _p2g_window(st.res, W, Q, *Ae, _channels(st.base))
  return out if extra is None else out[..., :5]


def _p2g_window_sum(G: int, W, Q, Ae0, Ae1, Ae2, base):
  """The (G, G, G, C) sum of every particle's window
  ``W (Q + o_x Ae0 + o_y Ae1 + o_z Ae2)`` at ``base`` (:func:`p2g`)."""
  o = [jnp.arange(3, dtype=W.dtype).reshape(s)
       for s in ((1, 3, 1, 1, 1), (1, 1, 3, 1, 1), (1, 1, 1, 3, 1))]
  U = W[..., None] * (Q + o[0] * Ae0 + o[1] * Ae1 + o[2] * Ae2)
  return _scatter(G, base, U)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _p2g_window(G: int, W, Q, Ae0, Ae1, Ae2, base):
  """:func:`_p2g_window_sum`, whose tangent on the CPU is formed as one
  product with the constant (27, 4) offset matrix, so that its transpose
  (the reverse pass) is that product too instead of XLA's reductions over
  the 27 nodes.

  XLA:CPU reduced the (N, 3, 3, 3, C) window cotangent over the nodes at
  about 1 GB/s: the tabletop's backward spent ~18 of its ~44 ms per
  substep there. The same sums as products (:func:`window_moments`' 'dot'
  form, which G2P's forward uses for the same reason) take a fraction of
  that. Elsewhere the tangent is XLA's own (``jax.jvp`` of the sum). A
  custom JVP (not a VJP): forward mode works too.
  """
  return _p2g_window_sum(G, W, Q, Ae0, Ae1, Ae2, base)


@_p2g_window.defjvp
def _p2g_window_jvp(G, primals, tangents):
  W, Q, Ae0, Ae1, Ae2, base = primals
  dW, dQ, dAe0, dAe1, dAe2, _ = tangents
  out = _p2g_window_sum(G, W, Q, Ae0, Ae1, Ae2, base)

  def by_products(W, Q, Ae0, Ae1, Ae2, base, dW, dQ, dAe0, dAe1, dAe2):
    # U_k = W_k V_k, V_k = sum_j o4_kj P_j with P = (Q, Ae0, Ae1, Ae2):
    # dU_k = W_k (o4 dP)_k + dW_k V_k, where o4 dP is one product with the
    # constant (27, 4) matrix over all particles. Its transpose is the same
    # product after W's elementwise one, and a sum over the C channels: the
    # reverse pass of a (6000, 32^3, C = 8) window took 1.0 ms this way,
    # 1.95 ms by the earlier custom VJP's batched products and 4.5 ms with
    # the tangent as per-particle products ('nk,kj,njc->nkc').
    n, c = W.shape[0], Q.shape[-1]
    o4 = _o4(W.dtype)                                              # (27, 4)
    P = jnp.stack([Q, Ae0, Ae1, Ae2], 1).reshape(n, 4, c)
    dP = jnp.stack([dQ, dAe0, dAe1, dAe2], 1).reshape(n, 4, c)
    hi = jax.lax.Precision.HIGHEST
    V = jnp.einsum('kj,njc->nkc', o4, P, precision=hi)             # (N,27,C)
    dU = (W.reshape(n, 27, 1) * jnp.einsum('kj,njc->nkc', o4, dP,
                                           precision=hi)
          + dW.reshape(n, 27, 1) * V)
    return _scatter(G, base, dU.reshape(n, 3, 3, 3, c))

  def by_xla(W, Q, Ae0, Ae1, Ae2, base, dW, dQ, dAe0, dAe1, dAe2):
    return jax.jvp(lambda *a: _p2g_window_sum(G, *a, base),
                   (W, Q, Ae0, Ae1, Ae2), (dW, dQ, dAe0, dAe1, dAe2))[1]

  dout = platforms.platform_dependent(
    W, Q, Ae0, Ae1, Ae2, base, dW, dQ, dAe0, dAe1, dAe2,
    cpu=by_products, default=by_xla)
  return out, dout


def _scatter(G: int, base, U):
  """Adds the (N, 3, 3, 3, C) window ``U`` of each particle into a
  (G, G, G, C) grid at its (N, 3) stencil ``base``."""
  dn = jax.lax.ScatterDimensionNumbers(
    update_window_dims=(1, 2, 3, 4), inserted_window_dims=(),
    scatter_dims_to_operand_dims=(0, 1, 2))
  out = jnp.zeros((G, G, G, U.shape[-1]), U.dtype)
  # Indices are in bounds by construction (positions are clamped into the
  # grid; NaN positions are caught by run()'s checks): CLIP keeps even a
  # NaN-derived index inside the array.
  return jax.lax.scatter_add(out, base, U, dn,
                             mode=jax.lax.GatherScatterMode.CLIP)


def _window_moments_dot(w, o4, g):
  """``R[n, j, d] = sum_k w[n, k] o4[k, j] g[n, k, d]`` as one product."""
  return jnp.einsum('nk,kj,nkd->njd', w, o4, g,
                    precision=jax.lax.Precision.HIGHEST)


def _window_moments_sum(w, o4, g):
  """The same as broadcast products and one sum over the 27 nodes."""
  wo = w[:, :, None] * o4[None]                                   # (N, 27, 4)
  return jnp.sum(wo[:, :, :, None] * g[:, :, None, :], axis=1)


def _window_block(g4, base, lin=None):
  """(N, 27, C) node values of each particle's 3 x 3 x 3 window of a
  (G, G, G, C) grid (G2P's velocities, C = 3): one windowed gather of a
  (3, 3, 3, C) block at ``base`` (clamped per axis)."""
  del lin
  c = g4.shape[-1]
  dn = jax.lax.GatherDimensionNumbers(
    offset_dims=(1, 2, 3, 4), collapsed_slice_dims=(),
    start_index_map=(0, 1, 2))
  return jax.lax.gather(g4, base, dn, slice_sizes=(3, 3, 3, c),
                        mode=jax.lax.GatherScatterMode.CLIP).reshape(-1, 27, c)


def _window_rows(g4, base, lin):
  """The same window as nine gathers of 9 contiguous values: the three z
  nodes' three components of each (x, y) column of the window, from the
  flat grid at ``lin`` (the base node's flat index). XLA:CPU computes a
  gather's source index per element; rows of 9 take 1/9 of that index work
  (G2P's gather fusion ~1.0 -> ~0.6 CPU-ms per substep at 6,000 particles,
  docs/benchmarks.md). Equal
  to :func:`_window_block` for particles inside the grid (the solver clamps
  them there); a start past the grid is clamped on the flat array."""
  del base
  G = g4.shape[0]
  xy = np.arange(3)[:, None] * (G * G) + np.arange(3)[None, :] * G
  start = (lin[:, None] + jnp.asarray(xy.reshape(-1), lin.dtype)) * 3
  dn = jax.lax.GatherDimensionNumbers(
    offset_dims=(2,), collapsed_slice_dims=(), start_index_map=(0,))
  return jax.lax.gather(g4.reshape(-1), start[..., None], dn,
                        slice_sizes=(9,),
                        mode=jax.lax.GatherScatterMode.CLIP).reshape(-1, 27, 3)


def window_moments(w, o4, g, form: str = 'auto'):
  """``R = O^T (w * g)`` per particle: (N, 27) weights, (27, 4) rows
  ``(1, o_k)``, (N, 27, 3) node velocities -> (N, 4, 3).

  ``form``: ``'dot'`` (one batched product: what XLA:CPU runs fastest, 4x
  the sum's speed at 6,000 particles), ``'sum'`` (broadcast products and
  a reduction over the 27 nodes, which XLA:GPU fuses with the gather into
  one kernel, where the product is a GEMM after a transposed copy of the
  gathered block), or ``'auto'``: 'dot' on the CPU, 'sum' elsewhere
  (``platforms.platform_dependent``).
  """
  if form == 'dot':
    return _window_moments_dot(w, o4, g)
  if form == 'sum':
    return _window_moments_sum(w, o4, g)
  if form != 'auto':
    raise ValueError(f"window_moments: form must be 'auto', 'dot' or 'sum', "
                     f'got {form!r}.')
  return platforms.platform_dependent(w, o4, g, cpu=_window_moments_dot,
                                    default=_window_moments_sum)


def g2p(grid: GridSpec, st: Stencil, gv, form: str = 'auto'):
  """Gathers particle velocities and affine matrices from the grid.

  One ``gather`` takes the 3 x 3 x 3 x 3 block of node velocities of each
  particle from the (G, G, G, 3) grid (on the CPU as nine rows of 9
  contiguous values, :func:`_window_rows`); with ``O`` the (27, 4) rows
  ``(1, o_k)``, ``R = O^T (w * g)`` gives ``v_d = sum_k w_k g_kd`` and
  ``B_ed = sum_k w_k o_ke g_kd`` (:func:`window_moments`: one small
  product per particle on the CPU, a fused sum on GPUs). The grid velocity
  is materialised first (:func:`materialize`). On XLA:CPU (6,000
  particles, 32^3) this G2P is about 3x faster than 81 scalar gathers by
  flat index and per-component products, and the whole MLS-MPM substep
  about 2x (docs/benchmarks.md).

  Args:
    grid: static grid.
    st: the particles' stencil.
    gv: 3-tuple of grid velocity components [m/s], each (G, G, G) or
      flat (G^3,).
    form: how the window is reduced (:func:`window_moments`).

  Returns:
    ``(v, C)``: 3-tuple of (N,) velocities and nested-tuple C [1/s].
  """
  G = st.res
  g4 = jnp.stack([a.reshape(G, G, G) for a in gv], axis=-1)      # (G,G,G,3)
  g4 = materialize(g4)
  base = _channels(st.base)                                       # (N, 3)
  g = platforms.platform_dependent(g4, base, st.lin, cpu=_window_rows,
                                 default=_window_block)           # (N,27,3)
  R = window_moments(st.weights(), _o4(g.dtype), g, form)         # (N, 4, 3)
  v = tuple(R[:, 0, d] for d in range(3))
  s = 4.0 * grid.inv_dx
  C = tuple(tuple(s * (R[:, 1 + e, d] - st.f[e] * v[d]) for e in range(3))
            for d in range(3))
  return v, C
