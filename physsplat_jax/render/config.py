"""Static rasterizer settings and the render result (see :mod:`.raster`)."""

from __future__ import annotations

import dataclasses
import math

import jax

from physsplat_jax import platforms
from physsplat_jax import struct
from physsplat_jax.errors import PhysSplatError
from physsplat_jax.types import Array

RASTERIZE_MODES = ('classic', 'antialiased')


class RenderConfigError(PhysSplatError, ValueError):
  """A :class:`RenderConfig` field has a value it cannot take."""


class RenderCapacityError(PhysSplatError, RuntimeError):
  """A render that still overflowed its intersection capacity after the
  allowed re-runs; the message names the capacity to pass."""


class RenderInputError(PhysSplatError, ValueError):
  """Something given to the renderer (Gaussians, camera, arrays, image)
  has a shape or value it cannot take."""


@dataclasses.dataclass(frozen=True)
class RenderConfig:
  """Static rasterizer settings (hashable; any change recompiles).

  Attributes:
    tile_size: tile edge [pixels] (gsplat and INRIA use 16).
    capacity: number of (Gaussian, tile) intersection slots; None means
      ``max(capacity_factor * K, min_capacity)``. Overflow sets
      ``RenderOutput.overflow``; :func:`render_image` then re-runs larger.
    capacity_factor: slots per Gaussian when ``capacity`` is None.
    min_capacity: lower bound of the automatic capacity.
    chunk_size: Gaussians composited per step of a tile (C).
    max_chunks: differentiable path only: chunks per tile (static trip
      count); None means enough for every Gaussian in one tile,
      ``ceil(min(K, capacity) / C)``, exact but slow for large scenes (use
      :func:`fit_render_config`).
    tile_batch: tiles processed together by ``lax.map`` (1 is fastest on a
      2-core CPU; larger batches help GPUs).
    eps2d: low-pass variance added to the 2D covariance [pixels^2].
    rasterize_mode: 'classic' (3DGS/INRIA, gsplat's default) or
      'antialiased' (gsplat ``rasterize_mode='antialiased'``, Mip-Splatting's
      2D filter): each opacity is scaled by ``sqrt(det(Sigma_2d) /
      det(Sigma_2d + eps2d I))`` so the low-pass blur conserves a splat's
      weight. Use it for scenes trained in that mode; it changes the image.
    alpha_max: alpha cap (gsplat 0.999; INRIA 0.99).
    alpha_min: alphas below this are skipped (1/255).
    t_min: transmittance at which a pixel stops (exclusive), 1e-4.
    sh_degree: SH degree to evaluate (None: all the coefficients given).
    prefix: 'matmul' (triangular-matrix prefix sum, fastest on CPU) or
      'cumsum'.
    subtile_size: edge of the compositing sub-tiles [pixels], dividing
      ``tile_size`` (None: the tile). Each sub-tile composites only the
      Gaussians of its tile that can reach it (see ``tight_bounds``); the
      image is the same, the work smaller for small splats.
    tight_bounds: bin each Gaussian only where its alpha can reach
      ``alpha_min``: inside the ellipse ``sigma <= log(opacity /
      alpha_min)`` (per-axis box), intersected with gsplat's 3-sigma tile
      rectangle. Exact: the pixels left out would all be skipped.
    backend: compositor: 'jax' (this module's, CPU reference), 'pallas'
      (:mod:`~physsplat_jax.render.pallas_raster`, Triton kernels with a
      back-to-front VJP) or 'auto' (Pallas on a GPU if the sub-tile edge
      and ``pallas_block`` are powers of two, JAX elsewhere). Same
      images, same API; the Pallas path is differentiable in both
      :func:`render` and :func:`render_differentiable` and ignores
      ``max_chunks``/``chunk_size``/``prefix``/``tile_batch``.
    interpret: run the Pallas kernels in interpret mode (debug/tests: the
      only way to run ``backend='pallas'`` off a GPU).
    pallas_block: Pallas forward: slots composited between two checks
      that every pixel of the sub-tile has stopped (power of two).
    pallas_num_warps: Triton warps per program of both kernels (None:
      two pixels per thread, see :meth:`resolved_pallas`).
  """

  tile_size: int = 16
  capacity: int | None = None
  capacity_factor: float = 4.0
  min_capacity: int = 4096
  chunk_size: int = 64
  max_chunks: int | None = None
  tile_batch: int = 1
  eps2d: float = 0.3
  rasterize_mode: str = 'classic'
  alpha_max: float = 0.999
  alpha_min: float = 1.0 / 255.0
  t_min: float = 1e-4
  sh_degree: int | None = None
  prefix: str = 'matmul'
  subtile_size: int | None = 8
  tight_bounds: bool = True
  backend: str = 'auto'
  interpret: bool = False
  pallas_block: int = 32
  pallas_num_warps: int | None = None

  def __post_init__(self):
    if self.rasterize_mode not in RASTERIZE_MODES:
      raise RenderConfigError(
        f'RenderConfig.rasterize_mode is {self.rasterize_mode!r}; use '
        f"{' or '.join(repr(m) for m in RASTERIZE_MODES)} ('antialiased' for "
        'scenes trained with gsplat\'s antialiased mode / Mip-Splatting)')

  @property
  def antialiased(self) -> bool:
    """True in gsplat's antialiased mode (opacity compensation)."""
    return self.rasterize_mode == 'antialiased'

  def resolved_backend(self) -> str:
    """'pallas' or 'jax'.

    ``backend='auto'`` gives Pallas on a GPU when the sub-tile edge and
    ``pallas_block`` are powers of two (Triton block shapes) and this JAX
    has Pallas's Triton backend, else JAX.
    """
    if self.backend != 'auto':
      return self.backend
    ok = self.pallas_shapes_ok and platforms.pallas_triton() is not None
    return 'pallas' if ok and jax.default_backend() == 'gpu' else 'jax'

  @property
  def pallas_shapes_ok(self) -> bool:
    """Sub-tile edge and ``pallas_block`` are powers of two (Triton)."""
    pow2 = lambda n: n >= 1 and (n & (n - 1)) == 0
    return pow2(self.resolved_subtile) and pow2(self.pallas_block)

  def resolved_pallas(self) -> tuple[int, int, int]:
    """(forward block, forward warps, backward warps) of the Pallas kernels.

    By default both kernels run two pixels per thread (``P / 64`` warps for
    the ``P`` pixels of a sub-tile, 1 to 32: one warp for 8x8 sub-tiles,
    so the backward's per-slot sums over the pixels stay inside a warp).
    Measured on an H100 (docs/benchmarks.md): the forward at 1M Gaussians,
    1024², took 2.79 ms with one warp against 3.23-3.48 ms with two (one
    pixel per thread), in two sessions.
    """
    p = self.resolved_subtile ** 2
    if self.pallas_num_warps is not None:
      return self.pallas_block, self.pallas_num_warps, self.pallas_num_warps
    warps = int(min(max(p // 64, 1), 32))
    return self.pallas_block, warps, warps

  @property
  def resolved_subtile(self) -> int:
    """Edge of the compositing sub-tiles [pixels]."""
    return self.tile_size if self.subtile_size is None else self.subtile_size

  def resolved_capacity(self, num_gaussians: int) -> int:
    """The slot count used for ``num_gaussians`` Gaussians."""
    if self.capacity is not None:
      return int(self.capacity)
    return max(
      int(math.ceil(self.capacity_factor * num_gaussians)), self.min_capacity
    )

  def resolved_max_chunks(self, num_gaussians: int) -> int:
    """Chunks per tile of the differentiable path."""
    if self.max_chunks is not None:
      return int(self.max_chunks)
    n = min(num_gaussians, self.resolved_capacity(num_gaussians))
    return max(1, -(-n // self.chunk_size))


class RenderOutput(struct.PyTreeNode):
  """Result of a render.

  Attributes:
    image: (H, W, 3) colour ``C + T bg`` (not clamped; SH colours are >= 0).
    alpha: (H, W) accumulated opacity ``1 - T``.
    depth: (H, W) expected camera depth ``sum(w z) / sum(w)`` [scene units],
      0 where nothing was drawn.
    overflow: () bool, True if intersections were dropped (capacity, or
      ``max_chunks`` on the differentiable path): the image is then wrong.
    num_intersections: () int32 (Gaussian, tile) pairs needed.
    max_tile_count: () int32 largest number of Gaussians in one compositing
      (sub-)tile.
    num_visible: () int32 Gaussians that survived culling.
  """

  image: Array
  alpha: Array
  depth: Array
  overflow: Array
  num_intersections: Array
  max_tile_count: Array
  num_visible: Array
