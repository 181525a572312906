"""Gaussian geometry and colour: quaternions, covariances, spherical harmonics.

- Quaternions are wxyz (Hamilton), as in INRIA 3DGS (``rot_0`` = w).
- ``covariance = R S S^T R^T`` with ``S = diag(exp(log_scales))``
  (INRIA ``build_covariance_from_scaling_rotation``; gsplat ``M = R * s``).
- Real SH up to degree 3 with the constants of INRIA ``utils/sh_utils.py``
  (Sloan 2013); colour = ``max(SH(dir) + 0.5, 0)``.

All functions are pure and batched over leading axes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from physsplat_jax.types import Array
from physsplat_jax.types import DataError

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (
  1.0925484305920792,
  -1.0925484305920792,
  0.31539156525252005,
  -1.0925484305920792,
  0.5462742152960396,
)
SH_C3 = (
  -0.5900435899266435,
  2.890611442640554,
  -0.4570457994644658,
  0.3731763325901154,
  -0.4570457994644658,
  1.445305721320277,
  -0.5900435899266435,
)


# Quaternions ----------------------------------------------------------------
def normalize_quat(q: Array, eps: float = 1e-12) -> Array:
  """Unit quaternions; a zero quaternion maps to the identity."""
  n2 = jnp.sum(q * q, axis=-1, keepdims=True)
  ok = n2 > eps
  ident = jnp.zeros_like(q).at[..., 0].set(1.0)
  safe = jnp.where(ok, q, ident)
  return safe / jnp.sqrt(jnp.sum(safe * safe, axis=-1, keepdims=True))


def _last_axis(fn: str, what: str, x, n: int, hint: str) -> None:
  """A DataError unless ``x`` is (..., n): JAX clamps an index past the end
  of an axis, so a (..., 3) quaternion gave a wrong rotation, silently."""
  shape = np.shape(x)
  if len(shape) < 1 or shape[-1] != n:
    raise DataError(f'{fn}: {what} have shape {shape}; give (..., {n}) '
                    f'({hint})')


def quat_to_rotmat(q: Array) -> Array:
  """(..., 4) wxyz quaternions (any norm) -> (..., 3, 3) rotation matrices."""
  _last_axis('quat_to_rotmat', 'quaternions', q, 4, 'wxyz')
  q = normalize_quat(q)
  w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
  r00 = 1 - 2 * (y * y + z * z)
  r01 = 2 * (x * y - w * z)
  r02 = 2 * (x * z + w * y)
  r10 = 2 * (x * y + w * z)
  r11 = 1 - 2 * (x * x + z * z)
  r12 = 2 * (y * z - w * x)
  r20 = 2 * (x * z - w * y)
  r21 = 2 * (y * z + w * x)
  r22 = 1 - 2 * (x * x + y * y)
  return jnp.stack(
    [
      jnp.stack([r00, r01, r02], -1),
      jnp.stack([r10, r11, r12], -1),
      jnp.stack([r20, r21, r22], -1),
    ],
    -2,
  )


def quat_to_rotmat_np(q) -> np.ndarray:
  """(K, 4) wxyz quaternions (any norm; zero -> identity) -> (K, 3, 3).

  NumPy float64 twin of :func:`quat_to_rotmat` for host-side code (export,
  filling, binding), which runs op by op where JAX would dispatch every op.
  """
  q = np.asarray(q, np.float64)
  n = np.linalg.norm(q, axis=-1, keepdims=True)
  q = np.where(n > 1e-12, q / np.where(n > 1e-12, n, 1.0), [1.0, 0, 0, 0])
  w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
  return np.stack([
    np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z),
              2 * (x * z + w * y)], -1),
    np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z),
              2 * (y * z - w * x)], -1),
    np.stack([2 * (x * z - w * y), 2 * (y * z + w * x),
              1 - 2 * (x * x + y * y)], -1),
  ], -2)


def rotmat_to_quat(R: Array) -> Array:
  """(..., 3, 3) proper rotations -> (..., 4) unit wxyz quaternions, w >= 0.

  Shepperd's method: picks the numerically largest of w, x, y, z branches.
  """
  R = jnp.asarray(R)
  m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
  m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
  m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
  tr = m00 + m11 + m22
  cands = jnp.stack(
    [
      jnp.stack([1 + tr, m21 - m12, m02 - m20, m10 - m01], -1),
      jnp.stack([m21 - m12, 1 + m00 - m11 - m22, m01 + m10, m02 + m20], -1),
      jnp.stack([m02 - m20, m01 + m10, 1 - m00 + m11 - m22, m12 + m21], -1),
      jnp.stack([m10 - m01, m02 + m20, m12 + m21, 1 - m00 - m11 + m22], -1),
    ],
    -2,
  )  # (..., 4 branches, 4)
  diag = jnp.stack([1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22,
                    1 - m00 - m11 + m22], -1)
  best = jnp.argmax(diag, axis=-1)
  q = jnp.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
  q = normalize_quat(q)
  return jnp.where(q[..., :1] < 0, -q, q)


def quat_multiply(a: Array, b: Array) -> Array:
  """Hamilton product of wxyz quaternions (rotation ``a`` after ``b``)."""
  aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
  bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
  return jnp.stack(
    [
      aw * bw - ax * bx - ay * by - az * bz,
      aw * bx + ax * bw + ay * bz - az * by,
      aw * by - ax * bz + ay * bw + az * bx,
      aw * bz + ax * by - ay * bx + az * bw,
    ],
    -1,
  )


# Covariances ------------------------------------------------------------------
def covariance(log_scales: Array, quats: Array) -> Array:
  """(..., 3, 3) covariance ``R S S^T R^T`` from log-scales and quaternions."""
  if np.shape(log_scales)[-1:] != (1,):  # (..., 1): isotropic, broadcast
    _last_axis('covariance', 'log-scales', log_scales, 3, 'x, y, z')
  R = quat_to_rotmat(quats)
  M = R * jnp.exp(log_scales)[..., None, :]
  return M @ jnp.swapaxes(M, -1, -2)


# Jitted forms for concrete inputs (``Gaussians.covariances`` and
# ``.rotations``): one compiled program per shape, where eager calls
# compiled one per operation (~14 ms each on the CPU).
quat_to_rotmat_jit = jax.jit(quat_to_rotmat)
covariance_jit = jax.jit(covariance)


def decompose_covariance(cov: Array, min_var: float = 1e-20):
  """Splits symmetric PSD covariances into log-scales and wxyz rotations.

  The inverse of :func:`covariance` up to the order and signs of the axes:
  ``covariance(*decompose_covariance(c)) == c``. The rotation is proper
  (det +1). Used to write deformed Gaussians (``F Sigma F^T``) back to PLY.
  Not for gradients: the axes of a covariance with equal eigenvalues (a
  round Gaussian) are arbitrary, and the derivative of the rotation there
  is NaN (the log-scales' is finite). Differentiate through covariances.

  Args:
    cov: (..., 3, 3) symmetric covariances.
    min_var: floor for the eigenvalues (degenerate Gaussians).

  Returns:
    (log_scales (..., 3), quats (..., 4)).
  """
  cov = 0.5 * (cov + jnp.swapaxes(cov, -1, -2))
  evals, evecs = jnp.linalg.eigh(cov)
  det = jnp.linalg.det(evecs)
  # Flip the last axis where the eigenbasis is a reflection.
  flip = jnp.where(det < 0, -1.0, 1.0).astype(evecs.dtype)
  evecs = evecs.at[..., :, 2].multiply(flip[..., None])
  log_scales = 0.5 * jnp.log(jnp.maximum(evals, min_var))
  return log_scales, rotmat_to_quat(evecs)


# Spherical harmonics -----------------------------------------------------
def sh_dc_to_rgb(sh_dc: Array) -> Array:
  """DC coefficient -> RGB (INRIA ``SH2RGB``), not clamped."""
  return 0.5 + SH_C0 * sh_dc


def rgb_to_sh_dc(rgb) -> Array:
  """RGB -> DC coefficient (INRIA ``RGB2SH``)."""
  return (jnp.asarray(rgb) - 0.5) / SH_C0


def sh_basis(degree: int, dirs: Array) -> Array:
  """Real SH basis values for unit directions.

  Args:
    degree: 0..3 (static).
    dirs: (..., 3) unit directions.

  Returns:
    (..., (degree + 1)**2) basis values, in the INRIA ordering and signs, so
    that ``colour = sum_b basis[b] * sh[b]`` matches ``eval_sh``.
  """
  if not 0 <= degree <= 3:
    raise DataError(f'SH degree must be 0..3, got {degree}')
  x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
  out = [jnp.full_like(x, SH_C0)]
  if degree >= 1:
    out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
  if degree >= 2:
    xx, yy, zz = x * x, y * y, z * z
    xy, yz, xz = x * y, y * z, x * z
    out += [
      SH_C2[0] * xy,
      SH_C2[1] * yz,
      SH_C2[2] * (2.0 * zz - xx - yy),
      SH_C2[3] * xz,
      SH_C2[4] * (xx - yy),
    ]
  if degree >= 3:
    out += [
      SH_C3[0] * y * (3 * xx - yy),
      SH_C3[1] * xy * z,
      SH_C3[2] * y * (4 * zz - xx - yy),
      SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
      SH_C3[4] * x * (4 * zz - xx - yy),
      SH_C3[5] * z * (xx - yy),
      SH_C3[6] * x * (xx - 3 * yy),
    ]
  return jnp.stack(out, axis=-1)


def eval_sh(sh: Array, dirs: Array, degree: int | None = None) -> Array:
  """View-dependent colour, INRIA/gsplat semantics: ``max(SH + 0.5, 0)``.

  Args:
    sh: (..., B, 3) coefficients.
    dirs: (..., 3) directions from the camera to the Gaussian (any length;
      normalised here).
    degree: SH degree to use (default: all of ``sh``).

  Returns:
    (..., 3) RGB, >= 0 (not clamped above, as in INRIA).
  """
  _last_axis('eval_sh', 'directions', dirs, 3, 'x, y, z')
  shape = np.shape(sh)
  if (len(shape) < 2 or shape[-1] != 3
      or round(np.sqrt(shape[-2])) ** 2 != shape[-2]):
    raise DataError(f'eval_sh: SH coefficients have shape {shape}; give '
                    '(..., B, 3) with B = (degree + 1)^2: 1, 4, 9 or 16')
  have = int(round(np.sqrt(sh.shape[-2]))) - 1
  if degree is None:
    degree = have
  if not 0 <= degree <= have:
    # (Else the einsum below broadcast a size-1 SH axis: wrong colours.)
    raise DataError(
      f'eval_sh: degree {degree} asked of SH coefficients of degree {have} '
      f'({sh.shape[-2]} per channel); use a degree in 0..{have}, or pad '
      'the coefficients with zeros (Gaussians.with_sh_degree)')
  n = jnp.sqrt(jnp.maximum(jnp.sum(dirs * dirs, -1, keepdims=True), 1e-24))
  basis = sh_basis(degree, dirs / n)
  nb = (degree + 1) ** 2
  rgb = jnp.einsum('...b,...bc->...c', basis, sh[..., :nb, :])
  return jnp.maximum(rgb + 0.5, 0.0)
