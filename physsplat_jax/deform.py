"""Gaussians that follow driving particles (PGAS's "local rigid fit").

PhysSplat simulates a sparse set of driving particles and moves every Gaussian
with its ``k`` nearest drivers. Binding is computed once on the host
(:func:`make_binding`); :func:`deform` is then a pure, jittable and
differentiable map ``driver positions (and F) -> Gaussian means, covariances,
rotations``.

Weighted local affine fit (default, ``driver_F=None``). For a Gaussian at rest
position ``X_g`` with neighbours ``j`` (rest ``X_j``, current ``x_j``) and
normalised weights ``w_j``::

  Xc = sum_j w_j X_j,   xc = sum_j w_j x_j
  M  = sum_j w_j (X_j - Xc)(X_j - Xc)^T          (rest moment, precomputed)
  F  = [sum_j w_j (x_j - xc)(X_j - Xc)^T] M^-1   (weighted least squares)
  x_g = xc + F (X_g - Xc)
  Sigma' = F Sigma F^T,   R = polar(F)

This is the least-squares affine map from the drivers' rest to current
positions, so any affine motion of the drivers (rigid motions, uniform
stretches) is reproduced exactly (to float rounding), and all outputs are
smooth functions of ``x_j``.

Interpolated deformation gradient (``driver_F`` given), as in PhysGaussian's
per-particle ``F`` but for a Gaussian between particles (first-order
extrapolation from each driver)::

  x_g = sum_j w_j (x_j + F_j (X_g - X_j)),   F = sum_j w_j F_j

Again exact for affine motions with ``F_j`` equal to the motion's gradient.

``R = polar(F)`` (rotation part of ``F = R S``) is the local rotation used to
rotate the SH view direction (PhysGaussian, Sec. 4.3). It is computed with a
scaled Newton iteration ``X <- (g X + X^-T / g) / 2`` (Higham 1986), which is
differentiable everywhere ``F`` is invertible, including ``F = I`` where an
SVD's gradient is NaN.

Weights: ``w_j ~ exp(-(d_j / h)^2)``, ``h`` the distance to the farthest of
the ``k`` neighbours (Gaussian kernel, normalised to sum 1).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from scipy import spatial

from physsplat_jax.types import Gaussians

Array = jax.Array

# Relative floor on the eigenvalues of the rest moment matrix M: drivers that
# are (nearly) coplanar or collinear around a Gaussian would make M singular.
_MOMENT_REL_FLOOR = 1e-6
_POLAR_ITERS = 10


class Binding(struct.PyTreeNode):
  """Precomputed Gaussian -> driver binding.

  Attributes:
    index: (K, k) int32 indices of each Gaussian's neighbouring drivers.
    weights: (K, k) normalised weights (rows sum to 1).
    rest_means: (K, 3) Gaussian centres at rest [scene units].
    rest_x: (K, k, 3) the neighbours' rest positions.
    rest_centroid: (K, 3) weighted rest centroid ``Xc``.
    moment_inv: (K, 3, 3) inverse of the weighted rest moment ``M``.
  """

  index: Array
  weights: Array
  rest_means: Array
  rest_x: Array
  rest_centroid: Array
  moment_inv: Array

  @property
  def k(self) -> int:
    return self.index.shape[1]


def make_binding(
  gauss_means, driver_rest_x, k: int = 8, dtype=None,
  gauss_object_ids=None, driver_object_ids=None,
) -> Binding:
  """Binds each Gaussian to its ``k`` nearest drivers (host side, not jitted).

  Args:
    gauss_means: (K, 3) Gaussian centres at rest.
    driver_rest_x: (N, 3) driving-particle rest positions, N >= 4 for the
      affine fit (at least 4 non-coplanar drivers per neighbourhood).
    k: neighbours per Gaussian, clipped to N.
    dtype: float dtype of the result (default: that of ``gauss_means``).
    gauss_object_ids, driver_object_ids: optional (K,) and (N,) object ids;
      when given, Gaussians bind only to drivers of their own object (so
      separate objects never drag each other).

  Returns:
    A :class:`Binding`.
  """
  gm = np.asarray(gauss_means)
  dx = np.asarray(driver_rest_x)
  dtype = dtype or (gm.dtype if np.issubdtype(gm.dtype, np.floating)
                    else np.float32)
  if gm.ndim != 2 or gm.shape[1] != 3:
    raise ValueError(f'gauss_means has shape {gm.shape}; expected (K, 3)')
  if dx.ndim != 2 or dx.shape[1] != 3:
    raise ValueError(f'driver_rest_x has shape {dx.shape}; expected (N, 3)')
  if dx.shape[0] < 4:
    raise ValueError(
      f'make_binding needs at least 4 driving particles, got {dx.shape[0]}; '
      'sample more drivers (smaller radius / larger budget).'
    )
  if not (np.all(np.isfinite(gm)) and np.all(np.isfinite(dx))):
    raise ValueError('make_binding: gauss_means or driver_rest_x has NaN/inf')
  if k < 4:
    raise ValueError(f'make_binding: k={k}; use k >= 4 for the affine fit')
  k = int(min(k, dx.shape[0]))
  gm64 = gm.astype(np.float64)
  dx64 = dx.astype(np.float64)
  if (gauss_object_ids is None) != (driver_object_ids is None):
    raise ValueError('make_binding: pass both gauss_object_ids and '
                     'driver_object_ids, or neither')
  if gauss_object_ids is None:
    dist, idx = spatial.cKDTree(dx64).query(gm64, k=k)
  else:
    go = np.asarray(gauss_object_ids)
    do = np.asarray(driver_object_ids)
    if go.shape != (len(gm64),) or do.shape != (len(dx64),):
      raise ValueError(f'make_binding: object ids have shapes {go.shape}, '
                       f'{do.shape}; expected ({len(gm64)},), ({len(dx64)},)')
    dist = np.zeros((len(gm64), k))
    idx = np.zeros((len(gm64), k), np.int64)
    for o in np.unique(go):
      gsel = np.nonzero(go == o)[0]
      dsel = np.nonzero(do == o)[0]
      if len(dsel) < k:
        raise ValueError(
          f'make_binding: object {o} has {len(dsel)} driving particles, '
          f'fewer than k={k}; sample more drivers for it or lower k')
      d_o, i_o = spatial.cKDTree(dx64[dsel]).query(gm64[gsel], k=k)
      dist[gsel] = d_o.reshape(len(gsel), k)
      idx[gsel] = dsel[i_o.reshape(len(gsel), k)]
  h = np.maximum(dist[:, -1:], 1e-12)
  w = np.exp(-((dist / h) ** 2))
  w = w / w.sum(1, keepdims=True)
  rest_x = dx64[idx]  # (K, k, 3)
  xc = np.einsum('kj,kjd->kd', w, rest_x)
  d = rest_x - xc[:, None]
  M = np.einsum('kj,kja,kjb->kab', w, d, d)
  ev, evec = np.linalg.eigh(M)
  floor = _MOMENT_REL_FLOOR * np.maximum(ev[:, -1:], 1e-30)
  ev = np.maximum(ev, floor)
  Minv = np.einsum('kab,kb,kcb->kac', evec, 1.0 / ev, evec)
  f = lambda a: jnp.asarray(a, dtype)
  return Binding(
    index=jnp.asarray(idx, jnp.int32),
    weights=f(w),
    rest_means=f(gm64),
    rest_x=f(rest_x),
    rest_centroid=f(xc),
    moment_inv=f(Minv),
  )


def _inv3(A: Array) -> Array:
  """Batched 3x3 inverse by cofactors (differentiable, no pivoting)."""
  a, b, c = A[..., 0, 0], A[..., 0, 1], A[..., 0, 2]
  d, e, f = A[..., 1, 0], A[..., 1, 1], A[..., 1, 2]
  g, h, i = A[..., 2, 0], A[..., 2, 1], A[..., 2, 2]
  co = jnp.stack(
    [
      jnp.stack([e * i - f * h, c * h - b * i, b * f - c * e], -1),
      jnp.stack([f * g - d * i, a * i - c * g, c * d - a * f], -1),
      jnp.stack([d * h - e * g, b * g - a * h, a * e - b * d], -1),
    ],
    -2,
  )
  det = a * co[..., 0, 0] + b * co[..., 1, 0] + c * co[..., 2, 0]
  return co / det[..., None, None]


def polar_rotation(F: Array, iters: int = _POLAR_ITERS) -> Array:
  """Rotation factor ``R`` of the polar decomposition ``F = R S``.

  Scaled Newton iteration (Higham 1986) with Frobenius-norm scaling. Exact
  (to rounding) when ``F`` is already orthogonal; differentiable for
  invertible ``F``. For ``det F < 0`` the result is the orthogonal factor
  (a reflection); deformation maps from the simulation have ``det F > 0``.

  Args:
    F: (..., 3, 3) invertible matrices.
    iters: number of Newton steps (10 converges to f32/f64 precision for
      condition numbers up to ~1e6).

  Returns:
    (..., 3, 3) orthogonal matrices.
  """
  X = F
  for _ in range(iters):
    Xit = jnp.swapaxes(_inv3(X), -1, -2)
    n1 = jnp.sqrt(jnp.sum(X * X, axis=(-1, -2)))
    n2 = jnp.sqrt(jnp.sum(Xit * Xit, axis=(-1, -2)))
    g = jnp.sqrt(n2 / n1)[..., None, None]
    X = 0.5 * (g * X + Xit / g)
  return X


def local_deformation(
  bind: Binding, driver_x: Array, driver_F: Array | None = None,
  rest_means: Array | None = None,
) -> tuple[Array, Array]:
  """Per-Gaussian current centre and local deformation gradient.

  Args:
    bind: from :func:`make_binding`.
    driver_x: (N, 3) current driver positions.
    driver_F: optional (N, 3, 3) driver deformation gradients; when given,
      ``F`` is interpolated instead of fitted.
    rest_means: optional (K, 3) rest centres (default ``bind.rest_means``).

  Returns:
    (means (K, 3), F (K, 3, 3)).
  """
  X_g = bind.rest_means if rest_means is None else rest_means
  w = bind.weights
  x = driver_x[bind.index]  # (K, k, 3)
  if driver_F is None:
    xc = jnp.einsum('kj,kjd->kd', w, x)
    dX = bind.rest_x - bind.rest_centroid[:, None]
    dx = x - xc[:, None]
    C = jnp.einsum('kj,kja,kjb->kab', w, dx, dX)
    F = C @ bind.moment_inv
    means = xc + jnp.einsum('kab,kb->ka', F, X_g - bind.rest_centroid)
  else:
    Fj = driver_F[bind.index]  # (K, k, 3, 3)
    off = X_g[:, None] - bind.rest_x
    pred = x + jnp.einsum('kjab,kjb->kja', Fj, off)
    means = jnp.einsum('kj,kjd->kd', w, pred)
    F = jnp.einsum('kj,kjab->kab', w, Fj)
  return means, F


def deform(
  bind: Binding,
  gaussians_or_means_covs,
  driver_x: Array,
  driver_F: Array | None = None,
) -> tuple[Array, Array, Array]:
  """Moves Gaussians with their driving particles.

  Args:
    bind: from :func:`make_binding`.
    gaussians_or_means_covs: the rest Gaussians, either a
      :class:`~physsplat_jax.types.Gaussians` or a tuple
      ``(means (K, 3), covariances (K, 3, 3))``.
    driver_x: (N, 3) current driver positions.
    driver_F: optional (N, 3, 3) driver deformation gradients.

  Returns:
    (means (K, 3), covariances (K, 3, 3) ``F Sigma F^T``, rotations (K, 3, 3)
    local rotation ``polar(F)``, for the SH view direction).
  """
  if isinstance(gaussians_or_means_covs, Gaussians):
    means0 = gaussians_or_means_covs.means
    covs0 = gaussians_or_means_covs.covariances
  else:
    means0, covs0 = gaussians_or_means_covs
  if means0.shape != bind.rest_means.shape:
    raise ValueError(
      f'deform: {means0.shape[0]} Gaussians but the binding was made for '
      f'{bind.rest_means.shape[0]}; call make_binding with these Gaussians.'
    )
  means, F = local_deformation(bind, driver_x, driver_F, rest_means=means0)
  covs = F @ covs0 @ jnp.swapaxes(F, -1, -2)
  R = polar_rotation(F)
  return means, covs, R


def deform_gaussians(
  bind: Binding, gaussians: Gaussians, driver_x: Array,
  driver_F: Array | None = None,
) -> Gaussians:
  """:func:`deform` returned as a :class:`Gaussians` (for PLY export/render).

  Scales and quaternions come from an eigen-decomposition of ``F Sigma F^T``
  (:func:`physsplat_jax.gaussians.decompose_covariance`); use :func:`deform`
  directly inside gradient computations.
  """
  from physsplat_jax import gaussians as _g

  means, covs, _ = deform(bind, gaussians, driver_x, driver_F)
  log_scales, quats = _g.decompose_covariance(covs)
  return gaussians.replace(
    means=means, log_scales=log_scales.astype(gaussians.log_scales.dtype),
    quats=quats.astype(gaussians.quats.dtype),
  )
