"""Brute-force NumPy reference rasterizer with gsplat semantics (for tests).

Written independently of :mod:`physsplat_jax.render.raster` and in float64:
every pixel composites ALL projected Gaussians whose 3-sigma tile rectangle
covers the pixel's tile, in global depth order, one Gaussian at a time
(gsplat ``cuda/_torch_impl.py:_rasterize_to_pixels`` / ``accumulate``):

  sigma = 0.5 (a dx^2 + c dy^2) + b dx dy,  alpha = min(alpha_max, o e^-sigma)
  skip if sigma < 0 or alpha < 1/255;  next_T = T (1 - alpha)
  if next_T <= 1e-4: the pixel stops (this Gaussian not blended)
  C += c alpha T;  T = next_T;  image = C + T bg.

``rasterize_mode='antialiased'`` (gsplat's, Mip-Splatting's 2D filter)
multiplies ``o`` by ``sqrt(max(det(cov2d) / det(cov2d + eps2d I), 0))``,
``cov2d`` being the projected covariance before the low-pass.

O(K H W): for scenes of a few hundred Gaussians at up to ~128 px.
"""

from __future__ import annotations

import math

import numpy as np

from physsplat_jax.render.config import RenderInputError


def project_numpy(means, covariances, viewmat, fx, fy, cx, cy, width, height,
                  near=0.01, far=1e10, eps2d=0.3):
  """EWA projection (see :mod:`physsplat_jax.render.project`), NumPy float64.

  Returns:
    dict with means2d (K, 2), conics (K, 3), depths (K,), radii (K,),
    valid (K,) bool, compensations (K,) (the antialiased mode's opacity
    factor; 0 where culled).
  """
  means = np.asarray(means, np.float64)
  covs = np.asarray(covariances, np.float64)
  V = np.asarray(viewmat, np.float64)
  fx, fy, cx, cy = (float(v) for v in (fx, fy, cx, cy))
  R, t = V[:3, :3], V[:3, 3]
  K = means.shape[0]
  out = dict(
    means2d=np.zeros((K, 2)), conics=np.zeros((K, 3)),
    depths=np.zeros(K), radii=np.zeros(K, np.int64),
    valid=np.zeros(K, bool), compensations=np.zeros(K),
  )
  tan_fovx = 0.5 * width / fx
  tan_fovy = 0.5 * height / fy
  lim_xp = (width - cx) / fx + 0.3 * tan_fovx
  lim_xn = cx / fx + 0.3 * tan_fovx
  lim_yp = (height - cy) / fy + 0.3 * tan_fovy
  lim_yn = cy / fy + 0.3 * tan_fovy
  for k in range(K):
    x, y, z = R @ means[k] + t
    out['depths'][k] = z
    if not near < z < far:
      continue
    tx = z * min(lim_xp, max(-lim_xn, x / z))
    ty = z * min(lim_yp, max(-lim_yn, y / z))
    J = np.array([[fx / z, 0.0, -fx * tx / z**2],
                  [0.0, fy / z, -fy * ty / z**2]])
    cov2d_orig = J @ R @ covs[k] @ R.T @ J.T
    cov2d = cov2d_orig + eps2d * np.eye(2)
    det = np.linalg.det(cov2d)
    if det <= 0:
      continue
    comp = math.sqrt(max(np.linalg.det(cov2d_orig) / det, 0.0))
    inv = np.linalg.inv(cov2d)
    mid = 0.5 * (cov2d[0, 0] + cov2d[1, 1])
    lam = mid + math.sqrt(max(mid * mid - det, 0.01))
    r = math.ceil(3.0 * math.sqrt(lam))
    u = fx * x / z + cx
    v = fy * y / z + cy
    if u + r <= 0 or u - r >= width or v + r <= 0 or v - r >= height:
      continue
    out['means2d'][k] = (u, v)
    out['conics'][k] = (inv[0, 0], inv[0, 1], inv[1, 1])
    out['radii'][k] = r
    out['valid'][k] = r > 0
    out['compensations'][k] = comp
  return out


def render_reference(means, covariances, colors, opacities, viewmat, fx, fy,
                     cx, cy, width, height, near=0.01, far=1e10,
                     background=(0.0, 0.0, 0.0), tile_size=16, eps2d=0.3,
                     alpha_max=0.999, alpha_min=1.0 / 255.0, t_min=1e-4,
                     rasterize_mode='classic'):
  """Renders with the brute-force reference.

  Args:
    means: (K, 3); covariances: (K, 3, 3); colors: (K, 3); opacities: (K,).
    viewmat, fx, fy, cx, cy, width, height, near, far: the camera.
    background: (3,) RGB.
    tile_size, eps2d, alpha_max, alpha_min, t_min: rasterizer constants.
    rasterize_mode: 'classic' or 'antialiased' (opacities times the
      compensations).

  Returns:
    (image (H, W, 3), alpha (H, W), depth (H, W)) float64, depth being the
    expected depth (0 where alpha is 0).
  """
  p = project_numpy(means, covariances, viewmat, fx, fy, cx, cy, width,
                    height, near, far, eps2d)
  colors = np.asarray(colors, np.float64)
  opac = np.asarray(opacities, np.float64)
  if rasterize_mode == 'antialiased':
    opac = opac * p['compensations']
  elif rasterize_mode != 'classic':
    raise RenderInputError(f'rasterize_mode {rasterize_mode!r}')
  H, W = int(height), int(width)
  jj, ii = np.meshgrid(np.arange(W), np.arange(H))
  px, py = jj + 0.5, ii + 0.5
  tx, ty = jj // tile_size, ii // tile_size
  T = np.ones((H, W))
  done = np.zeros((H, W), bool)
  rgb = np.zeros((H, W, 3))
  dep = np.zeros((H, W))
  order = np.argsort(p['depths'], kind='stable')
  for k in order:
    if not p['valid'][k]:
      continue
    (u, v), (a, b, c), r = p['means2d'][k], p['conics'][k], p['radii'][k]
    x0 = math.floor((u - r) / tile_size)
    x1 = math.ceil((u + r) / tile_size)
    y0 = math.floor((v - r) / tile_size)
    y1 = math.ceil((v + r) / tile_size)
    covered = (tx >= x0) & (tx < x1) & (ty >= y0) & (ty < y1)
    dx, dy = u - px, v - py
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha = np.minimum(alpha_max, opac[k] * np.exp(-sigma))
    use = covered & ~done & (sigma >= 0) & (alpha >= alpha_min)
    next_t = T * (1.0 - alpha)
    stop = use & (next_t <= t_min)
    blend = use & ~stop
    w = np.where(blend, alpha * T, 0.0)
    rgb += w[..., None] * colors[k]
    dep += w * p['depths'][k]
    T = np.where(blend, next_t, T)
    done |= stop
  alpha_img = 1.0 - T
  image = rgb + T[..., None] * np.asarray(background, np.float64)
  depth = np.where(alpha_img > 1e-6, dep / np.maximum(alpha_img, 1e-300), 0.0)
  return image, alpha_img, depth
