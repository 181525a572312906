"""Pure-JAX tile rasterizer for 3D Gaussian splats (gsplat semantics).

Pipeline (static shapes throughout, so it jits once per scene size and runs
unchanged on CPU and GPU):

1. :func:`~physsplat_jax.render.project.project`: EWA projection to conics
   (in ``rasterize_mode='antialiased'`` also gsplat's opacity compensation,
   which every later stage sees as the Gaussian's opacity).
2. Binning: each Gaussian covers the tiles ``[floor((m - r) / 16),
   ceil((m + r) / 16))`` in x and y (gsplat's 3-sigma rectangle). With
   ``tight_bounds`` this is intersected with the box of the ellipse where
   its alpha can reach 1/255, ``sigma <= log(255 o)``, whose half-widths are
   ``sqrt(2 log(255 o) Sigma2d_xx)`` and ``.._yy`` (the opacity-aware,
   per-axis extent of newer gsplat): every pixel left out would skip this
   Gaussian anyway, so the image is unchanged. Binning is done on
   ``subtile_size`` (8 px) sub-tiles, numbered tile by tile. The ``n_k``
   intersections of Gaussian ``k`` (in depth order) go to slots ``[s_k, s_k
   + n_k)`` of a buffer of STATIC size ``capacity`` (``s = cumsum(n) - n``);
   slot ``s`` finds its Gaussian as ``#{k: s_k + n_k <= s}`` (a histogram
   and a prefix sum). When ``sum(n) > capacity`` the output's ``overflow``
   flag is set (nothing is silently dropped: :func:`~physsplat_jax.render.
   images.render_image` re-runs with a larger capacity).
3. Gaussians are sorted by depth once (K keys); since slots are emitted in
   depth order, one stable sort on the sub-tile id alone orders every
   sub-tile's list front to back (cheaper than sorting (tile, depth)
   pairs); per-sub-tile ranges come from a ``searchsorted``.
4. Compositing per 16x16 tile, its four 8x8 sub-tiles side by side (each
   walks its own list), in chunks of ``C`` Gaussians, exactly as gsplat
   ``rasterize_to_pixels``::

     sigma = 0.5 (a dx^2 + c dy^2) + b dx dy,  dx = mean_x - (j + 0.5)
     alpha = min(0.999, o exp(-sigma));  skip if sigma < 0 or alpha < 1/255
     next_T = T (1 - alpha);  if next_T <= 1e-4: stop (exclusive: this
     Gaussian does not contribute);  C += c alpha T;  T = next_T
     image = C + T bg,  alpha_image = 1 - T.

   Inside a chunk the exclusive transmittance of every Gaussian is
   ``T0 exp(sum_{k<i} log(1 - alpha_k))``; the prefix sum is a matmul with a
   strictly upper-triangular matrix of ones, which is much faster than
   ``cumprod`` on CPU (REFERENCE 5.2) and identical up to rounding.

Two compositing loops share this code:

* :func:`render` (render-only): per tile, a ``lax.while_loop`` over chunks that
  stops when every sub-tile's list has ended or every pixel has stopped.
  Exact, fast, not reverse-differentiable.
* :func:`render_differentiable`: a static ``max_chunks`` per tile with a
  ``jax.checkpoint``-ed chunk body (memory: one carry per chunk). Sub-tiles
  with more than ``max_chunks * C`` Gaussians set ``overflow``.

On a GPU (``RenderConfig.backend='auto'``) stage 4 is replaced by the Pallas
(Triton) kernels of :mod:`~physsplat_jax.render.pallas_raster`, with the same
images and a back-to-front VJP; this module's compositor stays the CPU path
and the reference.

Colour is ``max(SH(dir) + 0.5, 0)`` with ``dir = mean - camera_position``
(world frame, INRIA ``computeColorFromSH``), or explicit per-Gaussian colours.
After a deformation, pass the deformed covariances ``F Sigma F^T`` and the
per-Gaussian rotations ``R`` (polar part of ``F``): the SH are then evaluated
at ``R^T dir``, the view direction in the Gaussian's rest frame, as
PhysGaussian's ``convert_SH`` does.

Differences between gsplat (followed here) and INRIA
``diff-gaussian-rasterization`` are listed in docs/rendering.md: alpha cap
0.999 vs 0.99, near plane 0.01 (camera.near) vs 0.2, frustum clamp
``(W - cx) / fx + 0.3 tan_fovx`` vs ``1.3 tan_fovx``. (Pixel centres at
``j + 0.5`` vs INRIA's ``j`` give the same image: INRIA moves the means by
the same half pixel.)
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from physsplat_jax import gaussians as gs
from physsplat_jax import platforms
from physsplat_jax import program_store
from physsplat_jax import sorting
from physsplat_jax import struct
from physsplat_jax.render.config import RenderConfig as RenderConfig
from physsplat_jax.render.config import RenderConfigError
from physsplat_jax.render.config import RenderInputError
from physsplat_jax.render.config import RenderOutput as RenderOutput
from physsplat_jax.render.project import Projected
from physsplat_jax.render.project import project
from physsplat_jax.types import Array
from physsplat_jax.types import Camera
from physsplat_jax.types import DataError
from physsplat_jax.types import Gaussians
from physsplat_jax.types import check_gaussians

# Exponent given to masked-out (Gaussian, pixel) pairs: exp(-1e10) == 0 with a
# zero (not NaN) derivative.
_MASKED_SIGMA = 1e10
_NUM_FEATURES = 10  # mean x, y; conic a, b, c; opacity; r, g, b; depth


# -----------------------------------------------------------------------------
# Input checks (shapes are static, so these run at trace time).


def _check_inputs(gaussians, camera, background, covariances, view_rotations,
                  colors, config):
  if not isinstance(gaussians, Gaussians):
    raise RenderInputError(
      f'render: gaussians must be a physsplat_jax.types.Gaussians, got '
      f'{type(gaussians).__name__}'
    )
  if not isinstance(camera, Camera):
    raise RenderInputError(
      f'render: camera must be a physsplat_jax.types.Camera, got '
      f'{type(camera).__name__} (build one with types.make_camera)'
    )
  try:   # shapes and dtypes only: the values may be traced
    K = check_gaussians(gaussians, 'render', finite=False,
                        sh=colors is None)
  except DataError as e:
    raise RenderInputError(str(e)) from None
  if K == 0:
    raise RenderInputError(
      'render: the scene has no Gaussians (K = 0); nothing to draw'
    )
  if covariances is not None and covariances.shape != (K, 3, 3):
    raise RenderInputError(
      f'render: covariances has shape {covariances.shape}; expected ({K}, 3, '
      '3), one 3x3 covariance per Gaussian (e.g. F Sigma F^T)'
    )
  if view_rotations is not None and view_rotations.shape != (K, 3, 3):
    raise RenderInputError(
      f'render: view_rotations has shape {view_rotations.shape}; expected '
      f'({K}, 3, 3), one rotation per Gaussian'
    )
  if colors is not None and colors.shape != (K, 3):
    raise RenderInputError(
      f'render: colors has shape {colors.shape}; expected ({K}, 3) RGB'
    )
  if colors is None and config.sh_degree is not None:
    # A degree above the coefficients given was silently wrong: eval_sh's
    # einsum broadcast a size-1 SH axis over the higher bands.
    have = gaussians.sh_degree
    if not 0 <= config.sh_degree <= have:
      raise RenderConfigError(
        f'RenderConfig.sh_degree={config.sh_degree}, but the Gaussians have '
        f'SH degree {have} (Gaussians.sh has shape {gaussians.sh.shape}); '
        f'use sh_degree=None (all they have) or a degree in 0..{have}, or '
        f'pad them with Gaussians.with_sh_degree({config.sh_degree}) (zero '
        'higher bands)'
      )
  if np.shape(background) != (3,):
    raise RenderInputError(
      f'render: background has shape {np.shape(background)}; expected (3,) '
      'RGB, e.g. (1, 1, 1) for white'
    )
  if camera.width < 1 or camera.height < 1:
    raise RenderInputError(
      f'render: camera size {camera.width}x{camera.height} must be positive'
    )
  if config.tile_size < 1 or config.chunk_size < 1:
    raise RenderConfigError(
      f'RenderConfig: tile_size ({config.tile_size}) and chunk_size '
      f'({config.chunk_size}) must be >= 1'
    )
  st = config.resolved_subtile
  if st < 1 or config.tile_size % st:
    raise RenderConfigError(
      f'RenderConfig.subtile_size ({config.subtile_size}) must divide '
      f'tile_size ({config.tile_size}); use e.g. 8 for 16-pixel tiles, or '
      'None'
    )
  if config.resolved_capacity(K) < 1:
    raise RenderConfigError(
      f'RenderConfig.capacity must be >= 1, got {config.capacity}'
    )
  if config.backend not in ('auto', 'jax', 'pallas'):
    raise RenderConfigError(
      f"RenderConfig.backend must be 'auto', 'jax' or 'pallas', got "
      f'{config.backend!r}'
    )
  if config.resolved_backend() == 'pallas':
    _check_pallas(config)
  if config.prefix not in ('matmul', 'cumsum'):
    raise RenderConfigError(
      f"RenderConfig.prefix must be 'matmul' or 'cumsum', got "
      f'{config.prefix!r}'
    )


def _check_pallas(config):
  st = config.resolved_subtile
  if platforms.pallas_triton() is None and not config.interpret:
    raise RenderConfigError(
      "RenderConfig: backend='pallas': " + platforms.triton_missing(
        "backend='auto' or 'jax' (scripts: "
        '--config.render_config.backend=auto)'))
  if not config.pallas_shapes_ok:
    raise RenderConfigError(
      f"RenderConfig: backend='pallas' needs a power-of-two sub-tile edge "
      f'and pallas_block (Triton block shapes), got {st} and '
      f'{config.pallas_block}'
    )
  if jax.default_backend() != 'gpu' and not config.interpret:
    raise RenderConfigError(
      f"RenderConfig: backend='pallas' runs on a GPU; on "
      f"'{jax.default_backend()}' use backend='auto' or 'jax' (scripts: "
      "--config.render_config.backend=auto), or interpret=True (slow, for "
      'tests)'
    )


# -----------------------------------------------------------------------------
# Stages.


def gaussian_colors(
  gaussians: Gaussians,
  camera: Camera,
  view_rotations: Array | None = None,
  sh_degree: int | None = None,
) -> Array:
  """View-dependent RGB of each Gaussian from its SH coefficients.

  Args:
    gaussians: K Gaussians (``means`` in the deformed/world frame).
    camera: the camera whose position sets the view directions.
    view_rotations: (K, 3, 3) or None; rotation of each Gaussian from its rest
      frame; the SH are evaluated at ``R^T (mean - camera_position)``.
    sh_degree: degree to evaluate (None: all).

  Returns:
    (K, 3) RGB >= 0.
  """
  dirs = gaussians.means - camera.position
  if view_rotations is not None:
    dirs = jnp.einsum('kji,kj->ki', view_rotations, dirs)
  return gs.eval_sh(gaussians.sh, dirs, sh_degree)


def _project(gaussians: Gaussians, covariances: Array | None,
             camera: Camera, config: RenderConfig) -> Projected:
  """EWA projection with the config's low-pass and rasterize mode."""
  dtype = gaussians.means.dtype
  covs = gaussians.covariances if covariances is None else covariances
  return project(gaussians.means, covs.astype(dtype), camera, config.eps2d,
                 antialiased=config.antialiased)


def _opacities(gaussians: Gaussians, proj: Projected) -> Array:
  """(K,) opacities to composite and bin.

  In ``rasterize_mode='antialiased'`` they carry gsplat's compensation, so
  the tight bounds and both compositors see it; 'classic' compiles to the
  program without it.
  """
  if proj.compensations is None:
    return gaussians.opacities
  return gaussians.opacities * proj.compensations


class _Binned(struct.PyTreeNode):
  gid: Array  # (capacity,) Gaussian of each sorted slot
  ranges: Array  # (num_subtiles + 1,) start of each sub-tile's slots
  total: Array  # () intersections needed
  max_tile: Array  # () largest sub-tile count


# Relative and absolute [pixels] slack of the tight bounds, far above float32
# round-off of the alpha test at the boundary.
_BOUND_RTOL = 1e-3
_BOUND_ATOL = 1e-2


def _footprints(proj: Projected, opacities: Array, tiles_x: int,
                tiles_y: int, config: RenderConfig):
  """Per-Gaussian sub-tile rectangles [x0, x0 + w) x [y0, ..) and counts n."""
  tile = config.tile_size
  st = config.resolved_subtile
  sub = tile // st
  m = lax.stop_gradient(proj.means2d)
  r = proj.radii.astype(m.dtype)
  # gsplat's tile rectangle [x0, x1) x [y0, y1) in tiles, in sub-tiles.
  fl = lambda v, hi: jnp.clip(jnp.floor(v / tile), 0, hi).astype(jnp.int32)
  ce = lambda v, hi: jnp.clip(jnp.ceil(v / tile), 0, hi).astype(jnp.int32)
  x0, x1 = sub * fl(m[:, 0] - r, tiles_x), sub * ce(m[:, 0] + r, tiles_x)
  y0, y1 = sub * fl(m[:, 1] - r, tiles_y), sub * ce(m[:, 1] + r, tiles_y)
  valid = proj.valid
  if config.tight_bounds:
    # alpha = o exp(-sigma) >= alpha_min  <=>  sigma <= log(o / alpha_min);
    # the ellipse 0.5 d^T Sigma2d^-1 d <= s spans +-sqrt(2 s Sigma2d_xx) in
    # x (Sigma2d = conic^-1).
    a, b, c = (lax.stop_gradient(proj.conics[:, i]) for i in range(3))
    det = a * c - b * b
    o = lax.stop_gradient(opacities)
    s_max = jnp.log(jnp.maximum(o, 1e-30) / config.alpha_min)
    valid = valid & (s_max > 0.0) & (det > 0.0)
    inv_det = 1.0 / jnp.where(det > 0.0, det, 1.0)
    two_s = 2.0 * jnp.maximum(s_max, 0.0)
    ex = jnp.sqrt(two_s * c * inv_det) * (1 + _BOUND_RTOL) + _BOUND_ATOL
    ey = jnp.sqrt(two_s * a * inv_det) * (1 + _BOUND_RTOL) + _BOUND_ATOL
    sfl = lambda v, hi: jnp.clip(jnp.floor(v / st), 0, hi).astype(jnp.int32)
    sce = lambda v, hi: jnp.clip(jnp.ceil(v / st), 0, hi).astype(jnp.int32)
    x0 = jnp.maximum(x0, sfl(m[:, 0] - ex, sub * tiles_x))
    x1 = jnp.minimum(x1, sce(m[:, 0] + ex, sub * tiles_x))
    y0 = jnp.maximum(y0, sfl(m[:, 1] - ey, sub * tiles_y))
    y1 = jnp.minimum(y1, sce(m[:, 1] + ey, sub * tiles_y))
  w = jnp.maximum(x1 - x0, 0)
  n = jnp.where(valid, w * jnp.maximum(y1 - y0, 0), 0)
  return x0, y0, w, n, valid


def _bin_and_sort(proj: Projected, opacities: Array, tiles_x: int,
                  tiles_y: int, config: RenderConfig,
                  capacity: int) -> _Binned:
  """Static-capacity (sub-tile, depth) binning; see the module docstring.

  Sub-tiles are numbered tile by tile (``tile * S + q``, ``S`` sub-tiles per
  tile, ``q`` row-major inside the tile), so a tile's sub-tiles are
  contiguous in the sorted list.
  """
  K = proj.depths.shape[0]
  sub = config.tile_size // config.resolved_subtile
  S = sub * sub
  x0, y0, w, n, valid = _footprints(proj, opacities, tiles_x, tiles_y,
                                    config)
  # Emit the intersections in depth order (one sort of K depths), then a
  # stable sort on the sub-tile id alone keeps each sub-tile front to back:
  # cheaper than sorting (tile, depth) pairs.
  # Both sorts are (unsigned key, int32) pairs: CUB's radix sort on a GPU
  # (physsplat_jax/sorting.py); depths of valid Gaussians are > 0.
  depth = jnp.where(valid, lax.stop_gradient(proj.depths), jnp.inf)
  order = sorting.argsort(depth)  # stable: ties by index
  n_o = n[order]
  ends = jnp.cumsum(n_o)
  total = ends[-1]
  starts = ends - n_o
  slots = jnp.arange(capacity, dtype=jnp.int32)
  # Slot s belongs to the k-th Gaussian (depth order) with k = #{ends <= s}:
  # a histogram of the ends and a prefix sum (O(K + capacity); a binary
  # search per slot is several times slower on CPU).
  hist = jnp.zeros((capacity + 1,), jnp.int32).at[
    jnp.minimum(ends, capacity)].add(1)
  k = jnp.minimum(jnp.cumsum(hist[:capacity]), K - 1)
  g = order[k]
  local = slots - starts[k]
  wg = jnp.maximum(w[g], 1)
  X = x0[g] + local % wg
  Y = y0[g] + local // wg
  tile_id = (Y // sub) * tiles_x + X // sub
  sub_id = tile_id * S + (Y % sub) * sub + X % sub
  num_sub = tiles_x * tiles_y * S
  sub_id = jnp.where(slots < total, sub_id, num_sub)
  sub_s, gid = sorting.sort_pairs(sub_id, g)
  ranges = _sub_tile_ranges(sub_s, num_sub)
  counts = ranges[1:] - ranges[:-1]
  return _Binned(gid=gid, ranges=ranges, total=total, max_tile=counts.max())


def _sub_tile_ranges(sub_s: Array, num_sub: int,
                     method: str | None = None) -> Array:
  """(num_sub + 1,) first slot of each sub-tile in the sorted ids ``sub_s``.

  A binary search per sub-tile: a loop on the CPU (``searchsorted``'s
  'scan'), unrolled elsewhere ('scan_unrolled': 5 kernels for an H100,
  where the loop's ~19 iterations were 76 kernel launches per render),
  chosen at lowering unless ``method`` forces one; both give the same
  ranges.
  """
  q = jnp.arange(num_sub + 1, dtype=jnp.int32)

  def search(m):
    return lambda: jnp.searchsorted(sub_s, q, side='left',
                                    method=m).astype(jnp.int32)

  if method is not None:
    return search(method)()
  return platforms.platform_dependent(cpu=search('scan'),
                                default=search('scan_unrolled'))


def _features(proj: Projected, colors: Array, opacities: Array) -> Array:
  """(K, 10) per-Gaussian data gathered by the compositor in one take."""
  valid = proj.valid
  conics = jnp.where(valid[:, None], proj.conics, jnp.array([1.0, 0.0, 1.0]))
  opac = jnp.where(valid, opacities, 0.0)
  depths = jnp.where(valid, proj.depths, 0.0)
  return jnp.concatenate(
    [proj.means2d, conics, opac[:, None], colors, depths[:, None]], axis=1
  )


def _tile_pixels(tiles_x: int, tile: int, st: int, t: Array, dtype):
  """Pixel-centre coordinates (S, st * st) of tile ``t``, per sub-tile."""
  sub = tile // st
  ty, tx = t // tiles_x, t % tiles_x
  q = jnp.arange(sub * sub)[:, None]
  p = jnp.arange(st * st)[None, :]
  j = (q % sub) * st + p % st
  i = (q // sub) * st + p // st
  px = (tx * tile + j).astype(dtype) + 0.5
  py = (ty * tile + i).astype(dtype) + 0.5
  return px, py


def _composite_chunk(feat, gid, px, py, base, end, carry, config, strict_upper,
                     guard):
  """Blends Gaussians ``[base, base + C) & [.., end)`` of each sub-tile.

  base, end: (S,) per sub-tile; px, py: (S, P) pixel centres;
  carry = (log_T (S, P), done (S, P) bool, acc (S, P, 4) rgb + depth).
  guard: mask negative exponents before ``exp`` (keeps reverse-mode
  gradients finite; not needed for the forward value).
  """
  log_t, done, acc = carry
  C = config.chunk_size
  log_t_min = math.log(config.t_min)
  idx = base[:, None] + jnp.arange(C, dtype=jnp.int32)  # (S, C)
  inside = idx < end[:, None]
  f = feat[gid[jnp.clip(idx, 0, gid.shape[0] - 1)]]  # (S, C, 10)
  # Slots past the list get opacity 0 (alpha 0 < alpha_min: skipped).
  opac = jnp.where(inside, f[..., 5], 0.0)[:, None, :]
  fx = lambda c: f[:, None, :, c]
  dx = fx(0) - px[..., None]  # (S, P, C)
  dy = fx(1) - py[..., None]
  sigma = 0.5 * (fx(2) * dx * dx + fx(4) * dy * dy) + fx(3) * dx * dy
  ok = sigma >= 0.0
  if guard:
    sigma = jnp.where(ok, sigma, _MASKED_SIGMA)
  alpha = jnp.minimum(config.alpha_max, opac * jnp.exp(-sigma))
  a = jnp.where(ok & (alpha >= config.alpha_min), alpha, 0.0)
  la = jnp.log1p(-a)  # (S, P, C); 0 for skipped Gaussians
  if config.prefix == 'matmul':
    excl = log_t[..., None] + la @ strict_upper
  else:
    excl = log_t[..., None] + jnp.cumsum(la, axis=-1) - la
  incl = excl + la
  # gsplat: the Gaussian whose next_T would be <= t_min stops the pixel and
  # is not blended; T is non-increasing, so the live ones form a prefix and
  # the pixel stops in this chunk iff the chunk's last incl is <= log t_min
  # (skipped Gaussians have la = 0 and blend nothing).
  live = (~done[..., None]) & (incl > log_t_min)
  vis = jnp.where(live, a * jnp.exp(excl), 0.0)
  acc = acc + jnp.einsum('spc,scf->spf', vis, f[..., 6:10])
  log_t = log_t + jnp.sum(jnp.where(live, la, 0.0), axis=-1)
  done = done | (incl[..., -1] <= log_t_min)
  return log_t, done, acc


def _rasterize(feat, binned, tiles_x, tiles_y, config, differentiable,
               max_chunks):
  tile = config.tile_size
  st = config.resolved_subtile
  S = (tile // st) ** 2
  P = st * st
  C = config.chunk_size
  dtype = feat.dtype
  strict_upper = jnp.triu(jnp.ones((C, C), dtype), 1)
  chunk = functools.partial(_composite_chunk, config=config,
                            strict_upper=strict_upper, guard=differentiable)

  def tile_fn(t):
    px, py = _tile_pixels(tiles_x, tile, st, t, dtype)
    start = lax.dynamic_slice(binned.ranges, (t * S,), (S,))
    end = lax.dynamic_slice(binned.ranges, (t * S + 1,), (S,))
    carry = (jnp.zeros((S, P), dtype), jnp.zeros((S, P), bool),
             jnp.zeros((S, P, 4), dtype))
    if differentiable:
      body = jax.checkpoint(
        lambda i, c: chunk(feat, binned.gid, px, py, start + i * C, end, c)
      )
      carry = lax.fori_loop(0, max_chunks, body, carry)
    else:
      num = jnp.max((end - start + C - 1) // C)

      def cond(s):
        i, c = s
        return (i < num) & ~jnp.all(c[1])

      def body(s):
        i, c = s
        return i + 1, chunk(feat, binned.gid, px, py, start + i * C, end, c)

      _, carry = lax.while_loop(cond, body, (jnp.int32(0), carry))
    log_t, _, acc = carry
    return log_t, acc

  tiles = jnp.arange(tiles_x * tiles_y, dtype=jnp.int32)
  batch = config.tile_batch if config.tile_batch > 1 else None
  return lax.map(tile_fn, tiles, batch_size=batch)


@jax.custom_vjp
def _no_reverse_pass(log_t, acc):
  """Identity whose reverse pass names the fix: the render-only
  compositor's early-stopping while loop has no reverse-mode derivative,
  and JAX's own error there says nothing about the renderer."""
  return log_t, acc


def _no_reverse_pass_fwd(log_t, acc):
  return (log_t, acc), None


def _no_reverse_pass_bwd(_, cts):
  raise RenderInputError(
    'render: gradient of an image from the render-only path '
    '(raster.render / render_image on the CPU path; in the pipeline '
    "render='fast'), which has no reverse pass: use "
    "raster.render_differentiable (pipeline: render='differentiable'), or "
    "put the loss on the Gaussians or particles (render='none')")


_no_reverse_pass.defvjp(_no_reverse_pass_fwd, _no_reverse_pass_bwd)


def _untile(x, tiles_x, tiles_y, tile, st, H, W):
  """(T, S, P, ...) per-sub-tile pixels -> (H, W, ...) image."""
  sub = tile // st
  rest = x.shape[3:]
  x = x.reshape((tiles_y, tiles_x, sub, sub, st, st) + rest)
  # (ty, tx, qy, qx, i, j) -> (ty, qy, i, tx, qx, j)
  x = jnp.transpose(x, (0, 2, 4, 1, 3, 5) + tuple(range(6, 6 + len(rest))))
  x = x.reshape((tiles_y * tile, tiles_x * tile) + rest)
  return x[:H, :W]


def _render(gaussians, camera, background, covariances, view_rotations,
            colors, config, differentiable):
  _check_inputs(gaussians, camera, background, covariances, view_rotations,
                colors, config)
  K = gaussians.means.shape[0]
  dtype = gaussians.means.dtype
  H, W = camera.height, camera.width
  tile = config.tile_size
  tiles_x = -(-W // tile)
  tiles_y = -(-H // tile)
  capacity = config.resolved_capacity(K)
  with jax.named_scope('project'):
    proj = _project(gaussians, covariances, camera, config)
    if colors is None:
      colors = gaussian_colors(gaussians, camera, view_rotations,
                               config.sh_degree)
    feat = _features(proj, colors.astype(dtype), _opacities(gaussians, proj))
  with jax.named_scope('bin_sort'):
    binned = _bin_and_sort(proj, feat[:, 5], tiles_x, tiles_y, config,
                           capacity)
  pallas = config.resolved_backend() == 'pallas'
  max_chunks = (config.resolved_max_chunks(K)
                if differentiable and not pallas else 0)
  with jax.named_scope('composite'):
    if pallas:
      from physsplat_jax.render import pallas_raster

      log_t, acc = pallas_raster.rasterize(feat, binned.gid, binned.ranges,
                                           tiles_x, tiles_y, config)
    else:
      log_t, acc = _rasterize(feat, binned, tiles_x, tiles_y, config,
                              differentiable, max_chunks)
      if not differentiable:
        log_t, acc = _no_reverse_pass(log_t, acc)
  st = config.resolved_subtile
  T = jnp.exp(_untile(log_t, tiles_x, tiles_y, tile, st, H, W))
  acc = _untile(acc, tiles_x, tiles_y, tile, st, H, W)
  rgb, dep = acc[..., :3], acc[..., 3]
  alpha = 1.0 - T
  bg = jnp.asarray(background, dtype)
  image = rgb + T[..., None] * bg
  drawn = alpha > 1e-6
  depth = jnp.where(drawn, dep / jnp.where(drawn, alpha, 1.0), 0.0)
  overflow = binned.total > capacity
  if differentiable and not pallas:
    overflow = overflow | (binned.max_tile > max_chunks * config.chunk_size)
  return RenderOutput(
    image=image,
    alpha=alpha,
    depth=depth,
    overflow=overflow,
    num_intersections=binned.total,
    max_tile_count=binned.max_tile,
    num_visible=jnp.sum(proj.valid).astype(jnp.int32),
  )


# -----------------------------------------------------------------------------
# Public API.


def render(
  gaussians: Gaussians,
  camera: Camera,
  *,
  background=(0.0, 0.0, 0.0),
  covariances: Array | None = None,
  view_rotations: Array | None = None,
  colors: Array | None = None,
  config: RenderConfig = RenderConfig(),
) -> RenderOutput:
  """Renders Gaussians (render-only path: exact, fast, not reverse-diff).

  Pure and jit-able (``jax.jit(render, static_argnames='config')``); the
  camera's size is static. Check ``overflow`` (or use :func:`render_image`).

  Args:
    gaussians: K Gaussians (``means``, ``log_scales``, ``quats``,
      ``opacity_logits``, ``sh`` are used).
    camera: the camera; ``camera.near``/``far`` clip by depth.
    background: (3,) RGB added with the remaining transmittance.
    covariances: (K, 3, 3) precomputed world covariances (e.g. ``F Sigma
      F^T`` after deformation) replacing ``log_scales``/``quats``.
    view_rotations: (K, 3, 3) per-Gaussian rotations; SH are evaluated at
      ``R^T (mean - camera_position)`` (PhysGaussian ``convert_SH``).
    colors: (K, 3) explicit RGB replacing the SH colour.
    config: static :class:`RenderConfig`.

  Returns:
    :class:`RenderOutput` with (H, W, 3) image, (H, W) alpha and depth.

  Raises:
    ValueError: on wrong shapes or settings (at trace time).
  """
  return _render(gaussians, camera, background, covariances, view_rotations,
                 colors, config, differentiable=False)


def render_differentiable(
  gaussians: Gaussians,
  camera: Camera,
  *,
  background=(0.0, 0.0, 0.0),
  covariances: Array | None = None,
  view_rotations: Array | None = None,
  colors: Array | None = None,
  config: RenderConfig = RenderConfig(),
) -> RenderOutput:
  """Renders Gaussians with a reverse-differentiable compositor.

  Same arguments and result as :func:`render`; gradients flow to the means,
  scales/quaternions or ``covariances``, opacities, SH or ``colors``,
  ``view_rotations`` and ``background``. Each tile runs
  ``config.max_chunks`` chunks of ``config.chunk_size`` Gaussians (static,
  each chunk rematerialised); ``overflow`` is also set when a tile holds more.
  Size the config on the host with :func:`fit_render_config`.
  """
  return _render(gaussians, camera, background, covariances, view_rotations,
                 colors, config, differentiable=True)


# Stored traced with a cache folder (program_store): a later process neither
# traces nor lowers the render (the host loop's frames, a video).
_render_jit = program_store.stored_jit(render, name='render',
                                       static_argnames=('config',))
_render_diff_jit = jax.jit(render_differentiable, static_argnames=('config',))


def _count_intersections(gaussians, camera, covariances, config):
  tile = config.tile_size
  tiles_x = -(-camera.width // tile)
  tiles_y = -(-camera.height // tile)
  proj = _project(gaussians, covariances, camera, config)
  n = _footprints(proj, _opacities(gaussians, proj), tiles_x, tiles_y,
                  config)[3]
  return jnp.sum(n)


_count_jit = program_store.stored_jit(_count_intersections,
                                      name='render_count',
                                      static_argnames=('config',))
