"""Gaussians that follow driving particles (PGAS's "local rigid fit").

PhysSplat simulates a sparse set of driving particles and moves every Gaussian
with its ``k`` nearest drivers. Binding is computed once on the host
(:func:`make_binding`); :func:`deform` is then a pure, jittable and
differentiable map ``driver positions (and F) -> Gaussian means, covariances,
rotations``.

Weighted local affine fit (default, ``driver_F=None``). For a Gaussian at rest
position ``X_g`` with neighbours ``j`` (rest ``X_j``, displacement
``u_j = x_j - X_j``) and normalised weights ``w_j``::

  Xc = sum_j w_j X_j,   uc = sum_j w_j u_j
  M  = sum_j w_j (X_j - Xc)(X_j - Xc)^T          (rest moment, precomputed)
  F  = I + [sum_j w_j (u_j - uc)(X_j - Xc)^T] M^+  (weighted least squares)
  x_g = X_g + uc + (F - I)(X_g - Xc)
  Sigma' = F Sigma F^T,   R = polar(F)

This is the least-squares affine map from the drivers' rest to current
positions, so any affine motion of the drivers (rigid motions, uniform
stretches) is reproduced exactly (to float rounding), and all outputs are
smooth functions of ``x_j``. Fitting the displacement (``F - I``) rather
than ``F`` makes the rest state exact: ``u_j = 0`` gives ``F = I`` and
``x_g = X_g`` bit for bit, whatever the drivers' geometry.

Degenerate neighbourhoods. Drivers that are coplanar (a Gaussian on a face
of a lattice of drivers) or collinear around a Gaussian leave ``M`` singular:
their motion says nothing about the directions ``v`` normal to their span
(eigenvalues of ``M`` below ``_MOMENT_REL_FLOOR`` times the largest). A
floored inverse of ``M`` maps those directions to ~0 (a singular ``F``: the
Gaussian is flattened and ``polar(F)`` is NaN). Instead ``M^+`` is the
pseudo-inverse on the spanned directions, and each degenerate direction is
completed with the rotation the spanned directions undergo:

* rank 2 (coplanar): ``F n = unit(F a x F b)`` for the rest plane's axes
  ``a, b`` and normal ``n = a x b``: the normal follows the plane's rotation
  and keeps its rest length (its stretch is unobservable);
* rank 1 (collinear, axis ``a``): both normals are turned by the smallest
  rotation taking ``a`` to ``unit(F a)``;
* rank 0 (all drivers at one point): ``F = I`` (translation only).

At rest every completion is the identity, so ``F = I`` for every Gaussian;
rigid motions stay exact in every case, and all maps are smooth in ``x_j``
away from ``F a x F b = 0`` (a plane folded flat). Interpolating the
drivers' own ``F`` (below) is the alternative, but needs ``driver_F``, which
the fit is there to avoid.

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

import jax.numpy as jnp
import numpy as np
import scipy

from physsplat_jax import struct
from physsplat_jax.errors import PhysSplatError
from physsplat_jax.types import Array
from physsplat_jax.types import Gaussians
from physsplat_jax.types import device_array


class DeformError(PhysSplatError, ValueError):
  """Bad input to the binding of Gaussians to their driving particles; the
  message names the array and the fix."""


# Relative threshold on the eigenvalues of the rest moment matrix M: below it
# (drivers spread along that direction by less than 1% of their largest
# spread, i.e. (nearly) coplanar or collinear drivers) the direction is
# degenerate and completed by a rotation (module docstring). Above it, the
# float32 noise of F - I in that direction stays ~1e-7 / 1% of the drivers'
# spacing / their spread.
_MOMENT_REL_FLOOR = 1e-4
# Squared-norm floor for normalisations in unused branches (finite gradients).
_TINY = 1e-30
_POLAR_ITERS = 10


class Binding(struct.PyTreeNode):
  """Precomputed Gaussian -> driver binding.

  Attributes:
    index: (K, k) int32 indices of each Gaussian's neighbouring drivers.
    weights: (K, k) normalised weights (rows sum to 1).
    rest_means: (K, 3) Gaussian centres at rest [scene units].
    rest_x: (K, k, 3) the neighbours' rest positions.
    rest_centroid: (K, 3) weighted rest centroid ``Xc``.
    moment_inv: (K, 3, 3) pseudo-inverse of the weighted rest moment ``M``
      (on its non-degenerate eigen-directions).
    rest_basis: (K, 3, 3) eigenvectors of ``M`` as columns, by decreasing
      eigenvalue, right-handed.
    rank: (K,) int32 number of non-degenerate directions of ``M`` (0-3).
  """

  index: Array
  weights: Array
  rest_means: Array
  rest_x: Array
  rest_centroid: Array
  moment_inv: Array
  rest_basis: Array
  rank: Array

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
    raise DeformError(f'gauss_means has shape {gm.shape}; expected (K, 3)')
  if dx.ndim != 2 or dx.shape[1] != 3:
    raise DeformError(f'driver_rest_x has shape {dx.shape}; expected (N, 3)')
  if dx.shape[0] < 4:
    raise DeformError(
      f'make_binding needs at least 4 driving particles, got {dx.shape[0]}; '
      'sample more drivers (smaller radius / larger budget).'
    )
  if not (np.all(np.isfinite(gm)) and np.all(np.isfinite(dx))):
    raise DeformError('make_binding: gauss_means or driver_rest_x has NaN/inf')
  if k < 4:
    raise DeformError(f'make_binding: k={k}; use k >= 4 for the affine fit')
  k = int(min(k, dx.shape[0]))
  gm64 = gm.astype(np.float64)
  dx64 = dx.astype(np.float64)
  if (gauss_object_ids is None) != (driver_object_ids is None):
    raise DeformError('make_binding: pass both gauss_object_ids and '
                      'driver_object_ids, or neither')
  if gauss_object_ids is None:
    dist, idx = scipy.spatial.cKDTree(dx64).query(gm64, k=k, workers=-1)
  else:
    go = np.asarray(gauss_object_ids)
    do = np.asarray(driver_object_ids)
    if go.shape != (len(gm64),) or do.shape != (len(dx64),):
      raise DeformError(f'make_binding: object ids have shapes {go.shape}, '
                        f'{do.shape}; expected ({len(gm64)},), ({len(dx64)},)')
    dist = np.zeros((len(gm64), k))
    idx = np.zeros((len(gm64), k), np.int64)
    for o in np.unique(go):
      gsel = np.nonzero(go == o)[0]
      dsel = np.nonzero(do == o)[0]
      if len(dsel) < k:
        raise DeformError(
          f'make_binding: object {o} has {len(dsel)} driving particles, '
          f'fewer than k={k}; sample more drivers for it or lower k')
      d_o, i_o = scipy.spatial.cKDTree(dx64[dsel]).query(
        gm64[gsel], k=k, workers=-1)
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
  ev, evec = ev[:, ::-1], evec[:, :, ::-1]  # decreasing
  evec[:, :, 2] *= np.sign(np.linalg.det(evec))[:, None]  # right-handed
  ok = ev > _MOMENT_REL_FLOOR * np.maximum(ev[:, :1], 1e-300)
  inv = np.where(ok, 1.0 / np.where(ok, ev, 1.0), 0.0)
  Minv = np.einsum('kab,kb,kcb->kac', evec, inv, evec)
  f = lambda a: device_array(a, dtype)
  return Binding(
    index=device_array(idx, jnp.int32),
    weights=f(w),
    rest_means=f(gm64),
    rest_x=f(rest_x),
    rest_centroid=f(xc),
    moment_inv=f(Minv),
    rest_basis=f(evec),
    rank=device_array(ok.sum(1), jnp.int32),
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


def _unit(v: Array) -> Array:
  return v / jnp.sqrt(jnp.sum(v * v, -1, keepdims=True) + _TINY)


def _complete_degenerate(A: Array, V: Array, rank: Array) -> Array:
  """Sets ``F v`` for the degenerate rest directions ``v`` (module docstring).

  Args:
    A: (K, 3, 3) fitted ``I + C M^+`` (identity on degenerate directions).
    V: (K, 3, 3) rest eigenvectors of ``M`` (columns, decreasing, det +1).
    rank: (K,) non-degenerate directions.

  Returns:
    (K, 3, 3) ``F`` with ``F V[:, r:]`` replaced by rotated rest axes.
  """
  a = jnp.einsum('kab,kbi->kia', A, V)  # a[:, i] = A v_i
  v = jnp.swapaxes(V, -1, -2)  # v[:, i] = v_i
  # Rank 2: the normal v_2 = v_0 x v_1 goes to unit(A v_0 x A v_1).
  n2 = _unit(jnp.cross(a[:, 0], a[:, 1]))
  # Rank 1: smallest rotation Q taking v_0 to e = unit(A v_0) (Rodrigues).
  e = _unit(a[:, 0])
  kx = jnp.cross(v[:, 0], e)
  c = jnp.sum(v[:, 0] * e, -1)
  q = lambda y: (c[:, None] * y + jnp.cross(kx, y) + kx * (
    jnp.sum(kx * y, -1) / jnp.maximum(1.0 + c, 1e-6))[:, None])
  r = rank[:, None]
  t1 = jnp.where(r == 1, q(v[:, 1]), a[:, 1])
  t2 = jnp.where(r == 2, n2, jnp.where(r == 1, q(v[:, 2]), a[:, 2]))
  # Rank 0 and the spanned directions keep A v_i.
  cols = jnp.stack([a[:, 0], t1, t2], 1)  # (K, 3 dirs, 3)
  return A + jnp.einsum('kia,kib->kab', cols - a, v)


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
    u = x - bind.rest_x
    uc = jnp.einsum('kj,kjd->kd', w, u)
    dX = bind.rest_x - bind.rest_centroid[:, None]
    C = jnp.einsum('kj,kja,kjb->kab', w, u - uc[:, None], dX)
    eye = jnp.eye(3, dtype=C.dtype)
    F = _complete_degenerate(eye + C @ bind.moment_inv, bind.rest_basis,
                             bind.rank)
    means = X_g + uc + jnp.einsum('kab,kb->ka', F - eye,
                                  X_g - bind.rest_centroid)
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
    raise DeformError(
      f'deform: {means0.shape[0]} Gaussians but the binding was made for '
      f'{bind.rest_means.shape[0]}; call make_binding with these Gaussians.'
    )
  means, F = local_deformation(bind, driver_x, driver_F, rest_means=means0)
  covs = F @ covs0 @ jnp.swapaxes(F, -1, -2)
  R = polar_rotation(F)
  return means, covs, R


def deform_gaussians(
  bind: Binding, gaussians: Gaussians, driver_x: Array,
  driver_F: Array | None = None, rotate_colors: bool = True,
) -> Gaussians:
  """:func:`deform` returned as a :class:`Gaussians` (for PLY export/render).

  Scales and quaternions come from an eigen-decomposition of ``F Sigma F^T``
  (:func:`physsplat_jax.gaussians.decompose_covariance`), and the SH
  coefficients are rotated by ``polar(F)``
  (:func:`physsplat_jax.sh_rotation.rotate_sh`), so that view-dependent
  colour turns with the object as ``render(..., view_rotations=R)`` shows
  it (``rotate_colors=False`` keeps the rest SH). Use :func:`deform`
  directly inside gradient computations; for files,
  :func:`physsplat_jax.io.export.deformed_gaussians` also keeps rigidly
  moved scales exact.

  An inverted driver (``det F < 0``, reached only by an over-compressed or
  unstable run) gives a reflection as ``polar(F)``: the covariance is still
  ``F Sigma F^T`` and the colours are mirrored with it (:func:`rotate_sh`
  is exact for any orthogonal matrix).
  """
  from physsplat_jax import gaussians as _g
  from physsplat_jax.sh_rotation import rotate_sh

  means, covs, R = deform(bind, gaussians, driver_x, driver_F)
  log_scales, quats = _g.decompose_covariance(covs)
  sh = gaussians.sh
  if rotate_colors:
    sh = rotate_sh(sh, R)  # (computed in sh's dtype)
  return gaussians.replace(
    means=means, log_scales=log_scales.astype(gaussians.log_scales.dtype),
    quats=quats.astype(gaussians.quats.dtype), sh=sh,
  )
