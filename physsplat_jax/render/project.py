"""EWA projection of 3D Gaussians to screen-space conics (gsplat semantics).

For a Gaussian with world mean ``mu`` and covariance ``Sigma`` seen by a camera
with world-to-camera rotation ``R`` and translation ``t`` (OpenCV axes):

  t_c = R mu + t,  Sigma_c = R Sigma R^T,
  J = [[fx / z, 0, -fx tx / z^2], [0, fy / z, -fy ty / z^2]],
  Sigma_2d = J Sigma_c J^T + eps2d I,          (EWA splatting, Zwicker 2002)
  conic = Sigma_2d^-1,  mean_2d = (fx x / z + cx, fy y / z + cy),
  radius = ceil(3 sqrt(lambda_max(Sigma_2d))).

In ``J`` the ratios ``x / z`` and ``y / z`` are clamped to the frustum limits
``lim_x+ = (W - cx) / fx + 0.3 tan_fovx`` and ``lim_x- = cx / fx + 0.3
tan_fovx`` (gsplat ``persp_proj``; INRIA clamps to ``+-1.3 tan_fovx``), so
Gaussians far off-axis do not get huge footprints. ``eps2d = 0.3`` is the
low-pass term of both gsplat and INRIA (a pixel-sized blur). Culled (invalid)
are Gaussians with ``z <= near`` or ``z >= far``, a non-positive 2D
determinant, or a 3-sigma box entirely off-screen.

With ``antialiased=True`` (gsplat ``rasterize_mode='antialiased'``, the 2D
Mip filter of Mip-Splatting, Yu et al. 2024) the low-pass also scales each
Gaussian's opacity by the compensation

  rho = sqrt(max(det(Sigma_2d') / det(Sigma_2d' + eps2d I), 0)),

``Sigma_2d' = J Sigma_c J^T`` being the covariance before the low-pass, so
the blur spreads a splat's weight instead of adding to it (a sub-pixel
Gaussian no longer renders as a pixel-sized blob of full opacity). gsplat
1.0-1.5 (``add_blur``) clamp the ratio at 0, as here.

Sources: gsplat ``cuda/_torch_impl.py`` (``_fully_fused_projection``,
``_persp_proj``); INRIA ``diff-gaussian-rasterization`` ``forward.cu``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from physsplat_jax import struct
from physsplat_jax.types import Array
from physsplat_jax.types import Camera

# Floor of the eigenvalue discriminant, as gsplat (``clamp(b^2 - det, 0.01)``).
_DISCRIMINANT_FLOOR = 0.01


class Projected(struct.PyTreeNode):
  """Screen-space Gaussians.

  Attributes:
    means2d: (K, 2) pixel coordinates of the centres (pixel (i, j) has its
      centre at ``(j + 0.5, i + 0.5)``).
    conics: (K, 3) upper triangle ``(a, b, c)`` of ``Sigma_2d^-1``, so the
      Gaussian's exponent at offset ``d`` is ``0.5 (a dx^2 + c dy^2) + b dx
      dy``.
    depths: (K,) camera-space z [scene units].
    radii: (K,) int32 pixel radius (3 sigma), 0 when culled.
    valid: (K,) bool, False for culled Gaussians.
    compensations: (K,) opacity factor ``rho`` of the antialiased mode
      (``project(..., antialiased=True)``), else None.
  """

  means2d: Array
  conics: Array
  depths: Array
  radii: Array
  valid: Array
  compensations: Array | None = None


def project(
  means: Array, covariances: Array, camera: Camera, eps2d: float = 0.3,
  antialiased: bool = False,
) -> Projected:
  """Projects 3D Gaussians to 2D conics with the EWA Jacobian.

  Args:
    means: (K, 3) world means [scene units].
    covariances: (K, 3, 3) world covariances.
    camera: the camera (OpenCV conventions, see :class:`Camera`).
    eps2d: low-pass variance added to the 2D covariance [pixels^2].
    antialiased: static; also return the opacity compensations of gsplat's
      antialiased mode (module docstring). False adds nothing to the
      program.

  Returns:
    A :class:`Projected`.
  """
  R = camera.viewmat[:3, :3]
  t = camera.viewmat[:3, 3]
  pc = means @ R.T + t
  x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
  W, H = camera.width, camera.height
  fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
  in_depth = (z > camera.near) & (z < camera.far)
  # Safe depth for culled Gaussians keeps the arithmetic (and grads) finite.
  zs = jnp.where(in_depth, z, 1.0)

  tan_fovx = 0.5 * W / fx
  tan_fovy = 0.5 * H / fy
  lim_xp = (W - cx) / fx + 0.3 * tan_fovx
  lim_xn = cx / fx + 0.3 * tan_fovx
  lim_yp = (H - cy) / fy + 0.3 * tan_fovy
  lim_yn = cy / fy + 0.3 * tan_fovy
  tx = zs * jnp.clip(x / zs, -lim_xn, lim_xp)
  ty = zs * jnp.clip(y / zs, -lim_yn, lim_yp)
  zero = jnp.zeros_like(zs)
  J = jnp.stack(
    [
      jnp.stack([fx / zs, zero, -fx * tx / (zs * zs)], -1),
      jnp.stack([zero, fy / zs, -fy * ty / (zs * zs)], -1),
    ],
    axis=-2,
  )  # (K, 2, 3)
  cov_c = R @ covariances @ R.T
  cov2d = J @ cov_c @ jnp.swapaxes(J, -1, -2)
  a = cov2d[:, 0, 0] + eps2d
  b = 0.5 * (cov2d[:, 0, 1] + cov2d[:, 1, 0])
  c = cov2d[:, 1, 1] + eps2d
  det = a * c - b * b
  ok_det = det > 0.0
  inv_det = 1.0 / jnp.where(ok_det, det, 1.0)
  conics = jnp.stack([c * inv_det, -b * inv_det, a * inv_det], -1)

  mid = 0.5 * (a + c)
  lam = mid + jnp.sqrt(jnp.maximum(mid * mid - det, _DISCRIMINANT_FLOOR))
  radius = jnp.ceil(3.0 * jnp.sqrt(jax.lax.stop_gradient(lam)))
  means2d = jnp.stack([fx * x / zs + cx, fy * y / zs + cy], -1)
  mx = jax.lax.stop_gradient(means2d[:, 0])
  my = jax.lax.stop_gradient(means2d[:, 1])
  on_screen = (
    (mx + radius > 0) & (mx - radius < W) & (my + radius > 0)
    & (my - radius < H)
  )
  valid = in_depth & ok_det & on_screen & (radius > 0)
  radii = jnp.where(valid, radius, 0).astype(jnp.int32)
  compensations = None
  if antialiased:
    # det before the low-pass over det after it; the ratio is clamped at 0
    # with a zero (not NaN) gradient there.
    det_orig = cov2d[:, 0, 0] * cov2d[:, 1, 1] - b * b
    ratio = det_orig * inv_det
    pos = ok_det & (ratio > 0.0)
    compensations = jnp.where(pos, jnp.sqrt(jnp.where(pos, ratio, 1.0)), 0.0)
  return Projected(
    means2d=means2d, conics=conics, depths=z, radii=radii, valid=valid,
    compensations=compensations,
  )
