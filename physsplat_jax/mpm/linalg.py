"""Batched 3x3 algebra written per component, polar decomposition and SVD.

Matrices inside the solver are *structure of arrays*: a 3x3 field over N
particles is a nested tuple ``M[i][j]`` of (N,) arrays (or an array of shape
(3, 3, N), which converts with :func:`to_mat` / :func:`from_mat`). XLA on CPU
handles arrays whose last axis is 3 or 9 badly (REFERENCE.md section 13), so
every product is written out by hand and unrolled at trace time.

Polar decomposition ``F = R S`` (R orthogonal, S symmetric positive definite)
by the scaled Newton iteration of Higham (1986)::

  R_0 = F,  R_{k+1} = (g_k R_k + g_k^{-1} R_k^{-T}) / 2,
  g_k = (|R_k^{-1}|_F / |R_k|_F)^{1/2}.

Its custom JVP differentiates the converged factor, not the iteration: with
``dR = R [w]_x`` and ``R^T dF - dF^T R = [(tr(S) I - S) w]_x``::

  a = axial(R^T dF - dF^T R),  w = (tr(S) I - S)^{-1} a,  dR = R [w]_x.

The map ``dF -> dR`` is self-adjoint, so the reverse pass (JAX's transpose
of it) is the same expression with a cotangent ``Rbar`` for ``dF``.
``tr(S) I - S`` has eigenvalues ``s_i + s_j > 0``, so the derivative is finite
everywhere ``F`` is invertible, including at ``F = I`` where SVD-based
gradients divide by ``s_i^2 - s_j^2 = 0`` (REFERENCE.md section 13: a plain
``jnp.linalg.svd`` gave NaN gradients there).

SVD ``F = U diag(s) V^T``: the forward pass is ``jnp.linalg.svd`` with signs
fixed so that ``U, V`` are rotations (a reflection goes into the smallest
singular value, Irving et al. 2004). ``svd`` has Townsend's (2016) JVP, split
into a ``1 / (s_j - s_i)`` part (its denominator clamped away from zero,
antisymmetrically, so that ``U^T dU`` stays skew) and
a regular ``1 / (s_j + s_i)`` part: finite everywhere, exact for distinct
singular values and for ``U V^T``, but at exactly repeated singular values it
drops limits of the form ``(g_j - g_i) / (s_j - s_i)`` (the factors U, V are
not differentiable there; only functions of F are).

For the constitutive models use :func:`make_spectral_map` instead: it
differentiates whole matrix functions

  F -> (U diag(h(s)) V^T,  U diag(k(s)) U^T,  aux(s))

of a permutation-symmetric map ``s -> (h, k, aux)`` (return maps on the
singular values, principal Kirchhoff stresses), with the divided
differences ``(h_j - h_i) / (s_j - s_i)`` replaced by their limit
``dh_i/ds_i - dh_i/ds_j`` (from the Jacobian of the map) when the singular
values are (nearly) equal. Its derivative is exact, including at F = I
(a Daleckii-Krein formula for the SVD).

Every rule here is a custom JVP, linear in the tangents: forward mode
(``jax.jvp``, ``jacfwd``) uses it as written, reverse mode (``grad``,
``vjp``, ``jacrev``) its transpose, which JAX derives. The rules can be
differentiated in turn (``jax.hessian``): exactly through
:func:`polar_mat`, also at F = I; through :func:`make_spectral_map` where
the singular values are distinct (its rule evaluates :func:`svd_mat`,
whose own derivative is a custom JVP), not at exactly repeated ones. Inside
``lax.scan`` (a rollout) take them reverse over forward (``jacrev`` of
``jacfwd``, ``grad`` of ``jvp``): forward over reverse, JAX has inlined the
primal functions of the rules when it partially evaluated the scan body for
the reverse pass, and the second pass differentiates the Jacobi sweeps
(NaN where a pair has converged; docs/mpm.md).
"""

from __future__ import annotations

import contextlib
import threading

import jax
import jax.numpy as jnp

from physsplat_jax import platforms
from physsplat_jax.types import Array

Mat = tuple  # tuple[tuple[Array, Array, Array], ...] of (N,) arrays


class _Mode(threading.local):
  on = False


# Set while a kernel body is traced (``kernel_mode``), in that thread only:
# primal code only.
_MODE = _Mode()


@contextlib.contextmanager
def kernel_mode():
  """Traces this module's functions for the body of a Pallas kernel: the
  forward computations only, without their custom JVPs (a kernel has no
  lowering for them; the caller differentiates the pure-JAX path instead),
  and the polar iteration and Jacobi sweeps as loops (no platform choice
  inside a kernel; unrolled, the tabletop's update took 5-8 s to compile
  for an H100, as loops 0.7-0.9 s). Same arithmetic, same values."""
  _MODE.on, old = True, _MODE.on
  try:
    yield
  finally:
    _MODE.on = old


# Scaled Newton iterations: 6 reach float32 round-off even for condition
# numbers ~4e4 (measured); float64 gets 9.
_POLAR_ITERS = {4: 6, 8: 9}
# Smallest |s_i^2 - s_j^2| used in the SVD gradient (relative to s^2).
_SVD_GAP = 1e-6


def to_mat(a: Array) -> Mat:
  """(3, 3, ...) array -> nested tuple ``M[i][j]``."""
  return tuple(tuple(a[i, j] for j in range(3)) for i in range(3))


def rows_mat(a: Array, first: int) -> Mat:
  """Nested tuple of the nine rows ``first .. first + 8`` of an (M, ...)
  array holding matrices row-major (``a[first + 3 i + j] = M[i][j]``)."""
  return tuple(tuple(a[first + 3 * i + j] for j in range(3))
               for i in range(3))


def mat_rows(m: Mat) -> tuple:
  """The nine fields of ``m`` in :func:`rows_mat`'s order."""
  return tuple(a for row in m for a in row)


def from_mat(m: Mat) -> Array:
  """Nested tuple ``M[i][j]`` -> (3, 3, ...) array."""
  return jnp.stack([jnp.stack(list(r)) for r in m])


def eye(like: Array) -> Mat:
  """Identity field shaped like ``like``."""
  o, z = jnp.ones_like(like), jnp.zeros_like(like)
  return ((o, z, z), (z, o, z), (z, z, o))


def zeros(like: Array) -> Mat:
  z = jnp.zeros_like(like)
  return ((z, z, z), (z, z, z), (z, z, z))


def add(a: Mat, b: Mat) -> Mat:
  return tuple(tuple(a[i][j] + b[i][j] for j in range(3)) for i in range(3))


def sub(a: Mat, b: Mat) -> Mat:
  return tuple(tuple(a[i][j] - b[i][j] for j in range(3)) for i in range(3))


def scale(a: Mat, s) -> Mat:
  return tuple(tuple(a[i][j] * s for j in range(3)) for i in range(3))


def transpose(a: Mat) -> Mat:
  return tuple(tuple(a[j][i] for j in range(3)) for i in range(3))


def matmul(a: Mat, b: Mat) -> Mat:
  return tuple(
    tuple(a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j]
          for j in range(3))
    for i in range(3)
  )


def matmul_t(a: Mat, b: Mat) -> Mat:
  """``a @ b^T``."""
  return tuple(
    tuple(a[i][0] * b[j][0] + a[i][1] * b[j][1] + a[i][2] * b[j][2]
          for j in range(3))
    for i in range(3)
  )


def t_matmul(a: Mat, b: Mat) -> Mat:
  """``a^T @ b``."""
  return tuple(
    tuple(a[0][i] * b[0][j] + a[1][i] * b[1][j] + a[2][i] * b[2][j]
          for j in range(3))
    for i in range(3)
  )


def add_diag(a: Mat, d) -> Mat:
  """``a + d I`` (d a scalar field)."""
  return tuple(
    tuple(a[i][j] + d if i == j else a[i][j] for j in range(3))
    for i in range(3)
  )


def diag(d0, d1, d2) -> Mat:
  z = jnp.zeros_like(d0)
  return ((d0, z, z), (z, d1, z), (z, z, d2))


def trace(a: Mat):
  return a[0][0] + a[1][1] + a[2][2]


def frob2(a: Mat):
  return sum(a[i][j] * a[i][j] for i in range(3) for j in range(3))


def cofactor(a: Mat) -> Mat:
  """Cofactor matrix: ``cof(A) = det(A) A^{-T}``."""
  return (
    (a[1][1] * a[2][2] - a[1][2] * a[2][1],
     a[1][2] * a[2][0] - a[1][0] * a[2][2],
     a[1][0] * a[2][1] - a[1][1] * a[2][0]),
    (a[0][2] * a[2][1] - a[0][1] * a[2][2],
     a[0][0] * a[2][2] - a[0][2] * a[2][0],
     a[0][1] * a[2][0] - a[0][0] * a[2][1]),
    (a[0][1] * a[1][2] - a[0][2] * a[1][1],
     a[0][2] * a[1][0] - a[0][0] * a[1][2],
     a[0][0] * a[1][1] - a[0][1] * a[1][0]),
  )


def det(a: Mat):
  return (a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
          - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
          + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0]))


def skew_from(w) -> Mat:
  """``[w]_x`` for a vector field ``w = (w0, w1, w2)``."""
  z = jnp.zeros_like(w[0])
  return ((z, -w[2], w[1]), (w[2], z, -w[0]), (-w[1], w[0], z))


def axial(a: Mat):
  """``(a21 - a12, a02 - a20, a10 - a01)`` (twice the axial vector)."""
  return (a[2][1] - a[1][2], a[0][2] - a[2][0], a[1][0] - a[0][1])


# Vectors with static components: a plane's normal is Python floats (the
# domain walls and a ground are axis-aligned), and a term with a Python zero
# is left out at trace time. The values are the same; the programs carry
# only the terms that are there (a GPU's fusion passes grow faster than a
# chain's length, and a plane normal to an axis costs one product per node
# or particle, not three).


def static_zero(q) -> bool:
  """Whether ``q`` is a Python number equal to 0 (known at trace time)."""
  return isinstance(q, (int, float)) and q == 0


def sum_products(terms):
  """``sum(a * b)`` over ``terms`` without the terms with a Python zero
  (0.0 if none is left)."""
  out = None
  for a, b in terms:
    if static_zero(a) or static_zero(b):
      continue
    t = a * b
    out = t if out is None else out + t
  return 0.0 if out is None else out


def vdot(a, b):
  """``a . b`` of 3-vectors whose components may be Python numbers."""
  return sum_products(zip(a, b))


def add_scaled(a, s, n):
  """``a + s n`` per component; where ``n`` has a Python zero the
  component is ``a``'s own."""
  return [a[d] if static_zero(n[d]) else a[d] + s * n[d] for d in range(3)]


def solve_sym(a: Mat, b):
  """``a^{-1} b`` for a symmetric positive definite field (cofactors)."""
  c = cofactor(a)
  d = det(a)
  return tuple((c[i][0] * b[0] + c[i][1] * b[1] + c[i][2] * b[2]) / d
               for i in range(3))


def _polar_newton(F: Mat, iters: int) -> Mat:
  if _MODE.on:
    # In a kernel a loop: the unrolled chain's code took seconds to compile.
    return jax.lax.fori_loop(0, iters, lambda _, X: _newton_step(X), F)
  X = F
  for _ in range(iters):
    X = _newton_step(X)
  return X


def _newton_step(X: Mat) -> Mat:
  """One scaled Newton step ``(g X + X^{-T} / g) / 2``."""
  c = cofactor(X)
  d = X[0][0] * c[0][0] + X[0][1] * c[0][1] + X[0][2] * c[0][2]
  # A singular F has no polar factor; keep the iteration finite (the
  # solver never lets det F reach 0, see constitutive.safe_J).
  # (A Python float: no negated constant array in a Pallas kernel.)
  tiny = 1e-30 if d.dtype == jnp.float64 else 1e-20
  d = jnp.where(jnp.abs(d) < tiny, jnp.where(d < 0, -tiny, tiny), d)
  # X^{-T} = cof(X) / det(X); scale by (|X^{-1}| / |X|)^{1/2}.
  n1 = frob2(X)
  n2 = frob2(c) / (d * d)
  g = jnp.sqrt(jnp.sqrt(n2 / n1))
  gi = 0.5 / (g * d)
  return tuple(tuple(0.5 * g * X[i][j] + gi * c[i][j] for j in range(3))
               for i in range(3))


def polar_mat(F: Mat) -> Mat:
  """Rotation factor ``R`` of ``F = R S`` (nested-tuple fields).

  Args:
    F: nested tuple of (N,) arrays, invertible matrices (det F > 0 gives a
      rotation; det F < 0 the orthogonal factor, a reflection).

  Returns:
    R as a nested tuple.
  """
  if _MODE.on:
    return _polar_newton(F, _iters(F))
  return _polar_mat(F)


@jax.custom_jvp
def _polar_mat(F: Mat) -> Mat:
  return _polar_newton(F, _iters(F))


def _iters(F):
  return _POLAR_ITERS.get(jnp.dtype(F[0][0].dtype).itemsize, 9)


@_polar_mat.defjvp
def _polar_jvp(primals, tangents):
  # dR = R [w]_x with [w]_x S + S [w]_x = R^T dF - dF^T R (module doc); the
  # map dF -> dR is self-adjoint, so its transpose (the reverse pass) is the
  # same expression.
  (F,), (dF,) = primals, tangents
  R = _polar_newton(F, _iters(F))
  S = t_matmul(R, F)
  S = tuple(tuple(0.5 * (S[i][j] + S[j][i]) for j in range(3))
            for i in range(3))
  A = add_diag(scale(S, -1.0), trace(S))
  w = solve_sym(A, axial(t_matmul(R, dF)))
  return R, matmul(R, skew_from(w))


def polar(F: Array) -> Array:
  """Rotation ``R`` of the polar decomposition ``F = R S``.

  Scaled Newton iteration with a custom JVP that is finite at ``F = I``.

  Args:
    F: (..., 3, 3) invertible matrices.

  Returns:
    (..., 3, 3) orthogonal matrices.
  """
  F = jnp.asarray(F)
  m = to_mat(jnp.moveaxis(F, (-2, -1), (0, 1)))
  return jnp.moveaxis(from_mat(polar_mat(m)), (0, 1), (-2, -1))


@jax.custom_jvp
def svd(F: Array):
  """Rotation-variant SVD ``F = U diag(s) V^T`` of (..., 3, 3) matrices.

  ``U`` and ``V`` are rotations (det +1); if ``det F < 0`` the smallest
  singular value is negative. The derivative (forward and reverse mode) is
  finite for repeated singular values.

  Args:
    F: (..., 3, 3) matrices.

  Returns:
    U (..., 3, 3), s (..., 3) in descending |s| order, V (..., 3, 3).
  """
  return _svd_fwd_impl(F)


def _svd_fwd_impl(F):
  U, s, Vt = jnp.linalg.svd(F)
  V = jnp.swapaxes(Vt, -1, -2)
  du = jnp.linalg.det(U)
  dv = jnp.linalg.det(V)
  fu = jnp.where(du < 0, -1.0, 1.0).astype(F.dtype)
  fv = jnp.where(dv < 0, -1.0, 1.0).astype(F.dtype)
  one = jnp.ones_like(fu)
  U = U * jnp.stack([one, one, fu], -1)[..., None, :]
  V = V * jnp.stack([one, one, fv], -1)[..., None, :]
  s = s * jnp.stack([one, one, fu * fv], -1)
  return U, s, V


@svd.defjvp
def _svd_jvp(primals, tangents):
  # With P = U^T dF V: ds = diag(P), dU = U Wu, dV = V Wv and, off the
  # diagonal, with sym / skw the symmetric / skew parts of P,
  #   Wu_ij = sym_ij / (s_j - s_i) + skw_ij / (s_j + s_i),
  #   Wv_ij = sym_ij / (s_j - s_i) - skw_ij / (s_j + s_i)
  # (Townsend 2016, split so that only the first term is singular). Both
  # denominators are clamped away from zero: finite everywhere, exact for
  # distinct singular values and for U V^T.
  (F,), (dF,) = primals, tangents
  U, s, V = _svd_fwd_impl(F)
  eye3 = jnp.eye(3, dtype=s.dtype)
  P = jnp.swapaxes(U, -1, -2) @ dF @ V
  Pt = jnp.swapaxes(P, -1, -2)
  sym = 0.5 * (P + Pt)
  skw = 0.5 * (P - Pt)
  sj = s[..., None, :]
  si = s[..., :, None]
  ref = jnp.maximum(jnp.max(jnp.abs(s), -1), 1e-30)[..., None, None]
  gap = _SVD_GAP * ref
  # Clamped keeping dm_ji = -dm_ij (ties broken by the index order), so
  # that Wu and Wv stay skew: U + dU remains a rotation to first order.
  upper = jnp.triu(jnp.ones((3, 3), bool), 1)
  dm = sj - si
  dp = sj + si
  neg = jnp.where(dm == 0, ~upper, dm < 0)
  dm = jnp.where(jnp.abs(dm) < gap, jnp.where(neg, -gap, gap), dm)
  dp = jnp.where(jnp.abs(dp) < gap, jnp.where(dp < 0, -gap, gap), dp)
  off = eye3 == 0
  Wu = jnp.where(off, sym / dm + skw / dp, 0.0)
  Wv = jnp.where(off, sym / dm - skw / dp, 0.0)
  ds = jnp.diagonal(P, axis1=-2, axis2=-1)
  return (U, s, V), (U @ Wu, ds, V @ Wv)


# ------------------------------------------------------------ spectral maps


# Cyclic Jacobi sweeps for the symmetric stretch S (quadratic convergence:
# 4 reach float32 round-off, 6 float64).
_JACOBI_SWEEPS = {4: 4, 8: 6}


def _jacobi_eigh(S: Mat, sweeps: int, unroll: bool | None = None):
  """Eigen-decomposition ``S = V diag(d) V^T`` of symmetric 3x3 fields.

  Cyclic Jacobi rotations on the pairs (0, 1), (0, 2), (1, 2), written per
  component (no batched LAPACK call, no (..., 3, 3) layout).

  ``unroll``: None chooses by platform at lowering (a loop on the CPU,
  unrolled elsewhere, see below); True or False forces one.

  Returns:
    ``(d, V)``: 3-tuple of eigenvalues (unsorted), V a rotation.
  """
  one = jnp.ones_like(S[0][0])
  zero = jnp.zeros_like(S[0][0])

  def sweep(_, carry):
    A, V = carry
    # Only the upper triangle of the symmetric A is carried (NR's update of
    # the rotated entries, a third of the full J^T A J): the Jacobi chain
    # is a large part of the substep's program, whose compile time grows
    # with its size.
    a = {(i, j): A[i][j] for i in range(3) for j in range(i, 3)}
    up = lambda i, j: (min(i, j), max(i, j))  # noqa: E731
    V = [list(r) for r in V]
    for p, q in ((0, 1), (0, 2), (1, 2)):
      r = 3 - p - q
      apq = a[p, q]
      off = apq == 0
      theta = (a[q, q] - a[p, p]) / (2.0 * jnp.where(off, one, apq))
      # Smaller root of t^2 + 2 theta t - 1 = 0; theta^2 may overflow to
      # inf, which gives t = 0 as it should.
      t = jnp.where(theta >= 0, one, -one) / (
        jnp.abs(theta) + jnp.sqrt(theta * theta + 1.0))
      t = jnp.where(off, zero, t)
      c = jax.lax.rsqrt(t * t + 1.0)
      sn = t * c
      # A <- J^T A J, V <- V J with J the rotation in the (p, q) plane:
      # the (p, q) entry vanishes, the diagonal moves by t a_pq.
      arp, arq = a[up(r, p)], a[up(r, q)]
      a[p, p] = a[p, p] - t * apq
      a[q, q] = a[q, q] + t * apq
      a[p, q] = zero
      a[up(r, p)] = c * arp - sn * arq
      a[up(r, q)] = sn * arp + c * arq
      for k in range(3):
        vkp, vkq = V[k][p], V[k][q]
        V[k][p] = c * vkp - sn * vkq
        V[k][q] = sn * vkp + c * vkq
    A = tuple(tuple(a[up(i, j)] for j in range(3)) for i in range(3))
    return (A, tuple(tuple(r) for r in V))

  V0 = tuple(tuple(one if i == j else zero for j in range(3))
             for i in range(3))

  # On the CPU a loop, not an unrolled chain: XLA:CPU would otherwise fuse
  # the whole chain into each consumer and recompute it many times over.
  # Elsewhere unrolled: on a GPU the loop is a while loop of its own inside
  # the substep (its state copied in, one kernel launch per sweep), the
  # unrolled chain one fusion with the rest of the stress update.
  def looped(carry):
    return jax.lax.fori_loop(0, sweeps, sweep, carry)

  def unrolled(carry):
    for i in range(sweeps):
      carry = sweep(i, carry)
    return carry

  carry = (tuple(S), V0)
  if unroll is None and _MODE.on:
    unroll = False
  if unroll is None:
    A, V = platforms.platform_dependent(carry, cpu=looped, default=unrolled)
  else:
    A, V = unrolled(carry) if unroll else looped(carry)
  return [A[0][0], A[1][1], A[2][2]], V


def svd_mat(F: Mat):
  """Rotation-variant SVD of a nested-tuple field.

  Structure of arrays throughout: ``F = R S`` by the scaled Newton polar
  iteration, then ``S = V diag(s) V^T`` by cyclic Jacobi and ``U = R V``,
  with the singular values sorted in descending order (several times
  faster on the CPU than a batched ``jnp.linalg.svd``, whose per-matrix
  LAPACK calls dominated the SVD-based material models). ``F`` must be
  invertible (the solver keeps ``det F`` away from 0).

  Its derivative is :func:`svd`'s (a custom JVP, exact for distinct
  singular values), not that of the Jacobi sweeps (NaN where an
  off-diagonal entry is 0). :func:`make_spectral_map`'s rule evaluates it,
  so that the rule can be differentiated in turn (``jax.hessian``).

  Returns:
    ``(U, s, V)``: U, V nested tuples (rotations), s a 3-tuple of (N,)
    singular values in descending order (the last negative if det F < 0).
  """
  if _MODE.on:
    return _svd_mat_impl(F)
  return _svd_mat(F)


@jax.custom_jvp
def _svd_mat(F: Mat):
  return _svd_mat_impl(F)


@_svd_mat.defjvp
def _svd_mat_jvp(primals, tangents):
  # _svd_jvp's formulas, per component.
  (F,), (dF,) = primals, tangents
  U, s, V = _svd_mat_impl(F)
  P = t_matmul(U, matmul(dF, V))                    # U^T dF V
  ref = jnp.maximum(jnp.maximum(jnp.maximum(jnp.abs(s[0]), jnp.abs(s[1])),
                                jnp.abs(s[2])), 1e-30)
  gap = _SVD_GAP * ref
  z = jnp.zeros_like(s[0])
  Wu = [[z] * 3 for _ in range(3)]
  Wv = [[z] * 3 for _ in range(3)]
  for i in range(3):
    for j in range(3):
      if i == j:
        continue
      dm = s[j] - s[i]
      neg = (dm < 0) if i < j else (dm <= 0)   # ties: dm_ji = -dm_ij
      dm = jnp.where(jnp.abs(dm) < gap, jnp.where(neg, -gap, gap), dm)
      dp = _safe_den(s[j] + s[i], ref, _SVD_GAP)
      sym = 0.5 * (P[i][j] + P[j][i])
      skw = 0.5 * (P[i][j] - P[j][i])
      Wu[i][j] = sym / dm + skw / dp
      Wv[i][j] = sym / dm - skw / dp
  dU = matmul(U, tuple(map(tuple, Wu)))
  dV = matmul(V, tuple(map(tuple, Wv)))
  return (U, s, V), (dU, tuple(P[i][i] for i in range(3)), dV)


def _svd_mat_impl(F: Mat):
  size = jnp.dtype(F[0][0].dtype).itemsize
  R = _polar_newton(F, _POLAR_ITERS.get(size, 9))
  S = t_matmul(R, F)
  S = tuple(tuple(0.5 * (S[i][j] + S[j][i]) for j in range(3))
            for i in range(3))
  d, V = _jacobi_eigh(S, _JACOBI_SWEEPS.get(size, 6))
  cols = [[V[k][i] for k in range(3)] for i in range(3)]

  def swap(i, j):
    # Sort step: exchanging two columns flips det V, so one of them is
    # negated to keep V a rotation.
    sw = d[i] < d[j]
    d[i], d[j] = jnp.where(sw, d[j], d[i]), jnp.where(sw, d[i], d[j])
    ci, cj = cols[i], cols[j]
    cols[i] = [jnp.where(sw, b, a) for a, b in zip(ci, cj)]
    cols[j] = [jnp.where(sw, -a, b) for a, b in zip(ci, cj)]

  swap(0, 1)
  swap(1, 2)
  swap(0, 1)
  V = tuple(tuple(cols[j][i] for j in range(3)) for i in range(3))
  U = [list(r) for r in matmul(R, V)]
  # det F < 0: R is a reflection; move it into the smallest singular value.
  flip = jnp.where(det(R) < 0, -1.0, 1.0).astype(d[0].dtype)
  for i in range(3):
    U[i][2] = U[i][2] * flip
  U = tuple(tuple(r) for r in U)
  return U, (d[0], d[1], d[2] * flip), V


def _gap(s):
  """Smallest |s_i - s_j| (relative) resolved by divided differences."""
  eps = jnp.finfo(s[0].dtype).eps
  return jnp.sqrt(eps)  # ~3e-4 (f32) / 1.5e-8 (f64)


def _safe_den(d, ref, gap):
  """``d`` pushed away from zero by ``gap * ref`` keeping its sign."""
  g = gap * ref
  return jnp.where(jnp.abs(d) < g, jnp.where(d < 0, -g, g), d)


def make_spectral_map(fn):
  """Differentiable matrix functions of the singular values of F.

  Args:
    fn: ``fn(s, p) -> (h, k, aux)`` with ``s`` a 3-tuple of (N,) singular
      values, ``p`` a pytree of (N,) float parameters, ``h`` and ``k``
      3-tuples of (N,) arrays and ``aux`` a pytree of (N,) arrays. It must be
      symmetric under permutations of ``s`` (isotropic material models are).

  Returns:
    ``apply(F, p) -> (Fh, Tk, aux)`` for a nested-tuple field ``F``:
    ``Fh = U diag(h(s)) V^T``, ``Tk = U diag(k(s)) U^T`` and ``aux(s)``, with
    a custom JVP that is exact at repeated singular values (module doc).
  """

  def forward(F, p):
    U, s, V = svd_mat(F)
    h, k, aux = fn(s, p)
    Fh = matmul_t(scale_cols(U, h), V)
    Tk = matmul_t(scale_cols(U, k), U)
    return (Fh, Tk, aux), (U, s, V, h, k, p)

  @jax.custom_jvp
  def apply(F, p):
    return forward(F, p)[0]

  @apply.defjvp
  def jvp(primals, tangents):
    # The tangent of Fh = U diag(h) V^T is U Qh V^T and that of
    # Tk = U diag(k) U^T is U Qk U^T with, for P = U^T dF V (sym / skw its
    # symmetric / skew parts) and the SVD's tangent (see _svd_jvp),
    #   Qh_ii = dh_i,  Qh_ij = Dh_ij sym_ij + Sh_ij skw_ij,
    #   Qk_ii = dk_i,  Qk_ij = Dk_ij (s_j P_ij + s_i P_ji) / (s_j + s_i),
    # Dh_ij = (h_j - h_i) / (s_j - s_i) (its limit from the map's Jacobian
    # where s_i ~ s_j), Sh_ij = (h_j + h_i) / (s_j + s_i). Linear in the
    # tangents: JAX transposes it for the reverse pass.
    (F, p), (dF, dp) = primals, tangents
    out, (U, s, V, h, k, _) = forward(F, p)
    P = t_matmul(U, matmul(dF, V))                  # U^T dF V
    ds = tuple(P[i][i] for i in range(3))
    _, (dh, dk, daux) = jax.jvp(fn, (s, p), (ds, dp))
    # Jacobians dh_i/ds_j, dk_i/ds_j for the repeated-value limits.
    zero_p = jax.tree.map(jnp.zeros_like, p)
    Jh, Jk = [], []
    for j in range(3):
      e = tuple(jnp.ones_like(s[0]) if i == j else jnp.zeros_like(s[0])
                for i in range(3))
      _, (dhj, dkj, _) = jax.jvp(fn, (s, p), (e, zero_p))
      Jh.append(dhj)
      Jk.append(dkj)
    # Jh[j][i] = dh_i / ds_j.
    ref = jnp.maximum(jnp.maximum(jnp.abs(s[0]), jnp.abs(s[1])),
                      jnp.abs(s[2]))
    ref = jnp.maximum(ref, jnp.finfo(s[0].dtype).tiny)
    gap = _gap(s)
    Qh = [[None] * 3 for _ in range(3)]
    Qk = [[None] * 3 for _ in range(3)]
    for i in range(3):
      Qh[i][i] = dh[i]
      Qk[i][i] = dk[i]
    for i in range(3):
      for j in range(3):
        if i == j:
          continue
        dm = s[j] - s[i]
        close = jnp.abs(dm) < gap * ref
        dm = _safe_den(dm, ref, gap)
        dps = _safe_den(s[j] + s[i], ref, gap)
        lim_h = 0.5 * (Jh[i][i] - Jh[j][i] + Jh[j][j] - Jh[i][j])
        lim_k = 0.5 * (Jk[i][i] - Jk[j][i] + Jk[j][j] - Jk[i][j])
        Dh = jnp.where(close, lim_h, (h[j] - h[i]) / dm)
        Dk = jnp.where(close, lim_k, (k[j] - k[i]) / dm)
        Sh = (h[j] + h[i]) / dps
        sym = 0.5 * (P[i][j] + P[j][i])
        skw = 0.5 * (P[i][j] - P[j][i])
        Qh[i][j] = Dh * sym + Sh * skw
        Qk[i][j] = Dk * (s[j] * P[i][j] + s[i] * P[j][i]) / dps
    dFh = matmul_t(matmul(U, tuple(map(tuple, Qh))), V)
    dTk = matmul_t(matmul(U, tuple(map(tuple, Qk))), U)
    return out, (dFh, dTk, daux)

  def apply_or_primal(F, p):
    if _MODE.on:
      return forward(F, p)[0]
    return apply(F, p)

  return apply_or_primal


def scale_cols(a: Mat, d) -> Mat:
  """``a @ diag(d)`` for a 3-tuple ``d`` of fields."""
  return tuple(tuple(a[i][j] * d[j] for j in range(3)) for i in range(3))
