"""Host-side rendering: never drops Gaussians, returns NumPy, may not wait.

:func:`render_image` calls the jitted :func:`~physsplat_jax.render.raster.
render` (or its differentiable twin) and re-runs it with a larger
``capacity`` when the overflow flag is set, so no Gaussian is ever dropped;
large scenes are counted first (:func:`count_intersections`) so one render
usually suffices. :func:`render_image_async` dispatches the same render and
returns a :class:`PendingRender` at once (JAX's asynchronous dispatch), so
a host loop can render one frame while it writes the previous one
(``pipeline.run``). :func:`fit_render_config` sizes a config for a view.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from physsplat_jax import program_store
from physsplat_jax.render import raster
from physsplat_jax.render.config import RenderCapacityError
from physsplat_jax.render.config import RenderConfig
from physsplat_jax.render.config import RenderInputError
from physsplat_jax.render.config import RenderOutput
from physsplat_jax.types import Array
from physsplat_jax.types import Camera
from physsplat_jax.types import DataError
from physsplat_jax.types import Gaussians
from physsplat_jax.types import check_camera
from physsplat_jax.types import check_gaussians
from physsplat_jax.types import nonfinite_rows
from physsplat_jax.types import rows_text

# pylint: disable=protected-access


def _next_capacity(needed: int, headroom: float = 1.1) -> int:
  """``needed`` times ``headroom`` (by default 10-25 % more), on a coarse
  grid of sizes.

  Sizes are multiples of 1/8 of a power of two (8 per octave), so similar
  frames share one compiled renderer, while the sort (which runs over the
  whole buffer) stays within 25 % of the work needed.
  """
  x = max(int(math.ceil(max(int(needed), 1) * max(float(headroom), 1.0))),
          1024)
  step = 2 ** max(int(math.floor(math.log2(x))) - 3, 0)
  return int(-(-x // step) * step)


def count_intersections(
  gaussians: Gaussians,
  camera: Camera,
  *,
  covariances: Array | None = None,
  config: RenderConfig = RenderConfig(),
) -> int:
  """(Gaussian, sub-tile) pairs a render needs (host side, cheap).

  Projection and counting only (no sort, no compositing), to size
  ``RenderConfig.capacity`` before the first render.
  """
  raster._check_inputs(gaussians, camera, (0.0, 0.0, 0.0), covariances,
                       None, None, config)
  return int(raster._count_jit(gaussians, camera.unlabelled(), covariances,
                               config))


def fit_render_config(
  gaussians: Gaussians,
  camera: Camera,
  config: RenderConfig = RenderConfig(),
  *,
  covariances: Array | None = None,
  margin: float = 1.25,
) -> RenderConfig:
  """Sizes ``capacity`` and ``max_chunks`` for a scene/camera (host side).

  Runs the render-only path once and returns a config whose capacity and
  per-tile chunk count fit this view with ``margin`` to spare (for the
  differentiable path, or for a sequence of similar frames).

  Args:
    gaussians: the Gaussians.
    camera: the camera.
    config: the starting config.
    covariances: optional precomputed covariances.
    margin: >= 1, head-room factor.

  Returns:
    A :class:`RenderConfig`.
  """
  out = render_image(gaussians, camera, covariances=covariances,
                     config=config)
  cap = int(math.ceil(max(int(out.num_intersections), 1) * margin))
  chunks = int(math.ceil(max(int(out.max_tile_count), 1) * margin
                         / config.chunk_size))
  return dataclasses.replace(config, capacity=max(cap, 1024),
                             max_chunks=chunks)


def start_host_copies(tree):
  """Starts the device-to-host copies of ``tree``'s arrays (returns it).

  Each copy starts as soon as its array is computed, while the host does
  other work, so a later fetch finds it on the host (a no-op on the CPU).
  """
  for leaf in jax.tree.leaves(tree):
    if isinstance(leaf, jax.Array):
      leaf.copy_to_host_async()
  return tree


# The image fields of a RenderOutput (the rest are scalar flags, always
# brought to the host).
IMAGE_FIELDS = ('image', 'alpha', 'depth')

# On the device: the image clipped to [0, 1] (the host's clip of a large
# frame took longer than the render on a GPU).
def _clip(image):
  return jnp.clip(image, 0.0, 1.0)


_clip_jit = program_store.stored_jit(_clip, name='render_clip')


class PendingRender:
  """A render dispatched by :func:`render_image_async`; :meth:`result` waits.

  Attributes:
    config: the config it ran with; after :meth:`result`, the one that fit
      (capacity grown on overflow): pass it to the next similar render to
      skip the counting pass and the re-runs.
    reruns: how many times :meth:`result` re-ran it larger (each new
      capacity is a new compiled program).
  """

  def __init__(self, fn, args: tuple, kwargs: dict, config: RenderConfig,
               num: int, differentiable: bool, max_retries: int,
               fetch: tuple[str, ...] = IMAGE_FIELDS, clip: bool = False,
               headroom: float = 1.1):
    self._fn, self._args, self._kwargs = fn, args, kwargs
    self._headroom = headroom
    self._num, self._differentiable = num, differentiable
    self._max_retries = max_retries
    self._clip = clip
    # What result() brings to the host: the flags and the fetched images.
    self._host = [f.name for f in dataclasses.fields(RenderOutput)
                  if f.name not in IMAGE_FIELDS or f.name in fetch]
    self.config = config
    self.reruns = 0
    self._out = self._run(config)
    self._result = None

  def _run(self, config) -> RenderOutput:
    """Dispatches the render; starts the copies of what :meth:`result`
    fetches."""
    out = self._fn(*self._args, config=config, **self._kwargs)
    if self._clip:
      out = out.replace(image=_clip_jit(out.image))
    start_host_copies([getattr(out, f) for f in self._host])
    return out

  def wait(self) -> 'PendingRender':
    """Waits until the device has computed the render (no fetch)."""
    if self._result is None:
      jax.block_until_ready(self._out)
    return self

  def result(self) -> RenderOutput:
    """The :class:`RenderOutput` as NumPy arrays (the image fields not in
    ``fetch`` stay JAX arrays on the device), never overflowing.

    Raises:
      RenderCapacityError: (a RuntimeError) still overflowing after
        ``max_retries`` re-runs.
    """
    if self._result is not None:
      return self._result
    config, K = self.config, self._num
    for attempt in range(self._max_retries + 1):
      if attempt:
        self.reruns += 1
        self._out = self._run(config)
      out = self._out.replace(**{
        f: np.asarray(getattr(self._out, f)) for f in self._host})
      if not bool(out.overflow):
        self.config, self._result, self._out = config, out, None
        self._args = self._kwargs = None
        return out
      total = int(out.num_intersections)
      if total > config.resolved_capacity(K):
        config = dataclasses.replace(
          config, capacity=_next_capacity(total, self._headroom))
      if self._differentiable:
        need = -(-int(out.max_tile_count) // config.chunk_size)
        if need > config.resolved_max_chunks(K):
          config = dataclasses.replace(config, max_chunks=need)
    raise RenderCapacityError(
      f'render_image: still overflowing after {self._max_retries} re-runs '
      f'(intersections {int(out.num_intersections)}, capacity '
      f'{config.resolved_capacity(K)}); pass a larger RenderConfig.capacity'
    )


def render_image_async(
  gaussians: Gaussians,
  camera: Camera,
  *,
  background=(0.0, 0.0, 0.0),
  covariances: Array | None = None,
  view_rotations: Array | None = None,
  colors: Array | None = None,
  config: RenderConfig = RenderConfig(),
  differentiable: bool = False,
  max_retries: int = 4,
  fetch: tuple[str, ...] = IMAGE_FIELDS,
  clip: bool = False,
  headroom: float = 1.1,
) -> PendingRender:
  """:func:`render_image` without waiting: dispatches and returns at once.

  The render runs on the device while the caller goes on (JAX's
  asynchronous dispatch); ``.result()`` waits for it, checks the overflow
  flag and re-runs larger if needed. Only a scene that needs counting
  first (no ``config.capacity`` and more than ``min_capacity /
  capacity_factor`` Gaussians) waits here, for the count: pass the
  ``.config`` of an earlier render of similar frames to avoid it.
  Arguments as for :func:`render_image`, and:

  Args:
    fetch: the image fields (``IMAGE_FIELDS``: 'image', 'alpha', 'depth')
      that ``.result()`` brings to the host (their copies start as soon as
      the render is done); the others stay JAX arrays on the device (a
      video needs only the image: a third of the bytes at 800x800).
    clip: clip the image to [0, 1] on the device.
    headroom: the capacity a count or an overflow sets, as a multiple of
      the intersections counted (then rounded up to 8 sizes per octave):
      more for the frames of a video, whose later frames may cover more of
      the image than the one counted (each larger capacity is a re-run and
      a new compiled renderer).
  """
  fn = raster._render_diff_jit if differentiable else raster._render_jit
  K = gaussians.means.shape[0]
  if config.capacity is None and (
    config.capacity_factor * K > config.min_capacity
  ):
    # Count first (cheap): one render at a fitting size instead of a render
    # that overflows and a second one (small scenes fit the minimum).
    need = count_intersections(gaussians, camera, covariances=covariances,
                               config=config)
    config = dataclasses.replace(config,
                                 capacity=_next_capacity(need, headroom))
  bad = sorted(set(fetch) - set(IMAGE_FIELDS))
  if bad:
    raise RenderInputError(f'render_image_async: fetch={tuple(fetch)!r} names '
                           f'{bad}; use some of {IMAGE_FIELDS}.')
  return PendingRender(
    fn, (gaussians, camera.unlabelled()),
    dict(background=jnp.asarray(background), covariances=covariances,
         view_rotations=view_rotations, colors=colors),
    config, K, differentiable, max_retries, fetch, clip, headroom)


# Relative tolerance, in units of the dtype's eps, of the symmetry and
# positive-definiteness checks of covariances: F Sigma F^T computed in
# float32 is symmetric only up to rounding, and the smallest eigenvalue of a
# flat Gaussian's covariance can round to slightly below zero.
_COV_EPS_UNITS = 64


def _not_spd_rows(covariances) -> tuple[np.ndarray, np.ndarray]:
  """Rows of a concrete (K, 3, 3) array that are not symmetric, and rows
  (of the symmetric ones) that are not positive definite, up to rounding.

  Positive definite by Sylvester's criterion (leading minors > 0) of
  ``C + tol |C|_max I``: a matrix positive semi-definite up to rounding
  passes, a negative, zero or indefinite one does not.
  """
  c = np.asarray(covariances)
  tol = _COV_EPS_UNITS * np.finfo(np.result_type(c.dtype, np.float32)).eps
  c = c.astype(np.float64)
  size = np.abs(c).max(axis=(1, 2))
  asym = np.abs(c - np.swapaxes(c, 1, 2)).max(axis=(1, 2)) > tol * size
  s = 0.5 * (c + np.swapaxes(c, 1, 2)) + (tol * size)[:, None, None] * \
    np.eye(3)
  a, b, c2 = s[:, 0, 0], s[:, 0, 1], s[:, 0, 2]
  d, e, f = s[:, 1, 1], s[:, 1, 2], s[:, 2, 2]
  m2 = a * d - b * b
  m3 = a * (d * f - e * e) - b * (b * f - e * c2) + c2 * (b * e - d * c2)
  not_pd = ~asym & ~((a > 0) & (m2 > 0) & (m3 > 0))
  return np.flatnonzero(asym), np.flatnonzero(not_pd)


def _check_covariances(K: int, covariances, view_rotations) -> None:
  """Refuses concrete non-finite ``covariances`` or ``view_rotations``
  (the Gaussian was dropped from the image without a word) and
  covariances that are not symmetric positive definite (drawn wrong
  without a word). Tracers are left alone."""
  given = {name: a for name, a in (('covariances', covariances),
                                    ('view_rotations', view_rotations))
           # (a wrong shape: the renderer's shape check says what is
           # expected)
           if a is not None and not isinstance(a, jax.core.Tracer)
           and np.shape(a) == (K, 3, 3)}
  for name, a in given.items():
    rows = nonfinite_rows(a)
    if rows.size:
      raise RenderInputError(
        f'render_image: {name} has non-finite values in {rows.size} of {K} '
        f'rows (rows {rows_text(rows)}); each row must be a finite 3x3 '
        'matrix (check the deformation gradients F that built them)')
  if 'covariances' not in given:
    return
  asym, not_pd = _not_spd_rows(covariances)
  for rows, what in ((asym, 'not symmetric'),
                     (not_pd, 'not positive definite')):
    if rows.size:
      first = np.asarray(covariances)[rows[0]]
      raise RenderInputError(
        f'render_image: covariances rows {rows_text(rows)} ({rows.size} of '
        f'{K}) are {what} (row {int(rows[0])}: '
        f'{np.round(first.astype(np.float64), 6).tolist()}); pass '
        'symmetric positive definite 3x3 covariances, e.g. '
        'Gaussians.covariances, or F Sigma F^T with an invertible F')


def render_image(
  gaussians: Gaussians,
  camera: Camera,
  *,
  background=(0.0, 0.0, 0.0),
  covariances: Array | None = None,
  view_rotations: Array | None = None,
  colors: Array | None = None,
  config: RenderConfig = RenderConfig(),
  differentiable: bool = False,
  max_retries: int = 4,
) -> RenderOutput:
  """Host wrapper: jitted render that never drops Gaussians; NumPy outputs.

  Without ``config.capacity``, scenes larger than ``min_capacity /
  capacity_factor`` Gaussians are first counted (:func:`count_intersections`)
  and rendered with that capacity plus head-room. Re-runs with a larger
  ``capacity`` (and ``max_chunks`` on the differentiable path) when a pass
  overflows. :func:`render_image_async` is the same without waiting.

  Args:
    gaussians, camera, background, covariances, view_rotations, colors,
      config: as for :func:`render`.
    differentiable: use :func:`render_differentiable` (for tests of that
      path).
    max_retries: re-runs allowed before giving up.

  Returns:
    :class:`RenderOutput` of NumPy arrays (``overflow`` is False).

  Raises:
    RenderInputError: non-finite values in the Gaussians, ``colors``,
      ``covariances``, ``view_rotations`` or ``background`` (which may also
      be a name: 'white', 'black', 'grey'); covariances that are not
      symmetric positive definite; wrong shapes.
    RenderCapacityError: (a RuntimeError) still overflowing after
      ``max_retries`` re-runs.
  """
  from physsplat_jax.render import views  # (views imports this module)

  if isinstance(background, str):
    background = views.parse_background(background)
  try:
    check_gaussians(gaussians, 'render_image', sh=colors is None)
    # (A camera from Camera.replace skipped make_camera's checks: near >
    # far or a NaN focal length rendered a black image.)
    check_camera(camera)
  except DataError as e:
    raise RenderInputError(str(e)) from None
  for name, a in (('colors', colors), ('background', background)):
    if a is not None and not np.all(np.isfinite(np.asarray(a))):
      raise RenderInputError(f'render_image: {name} has non-finite values')
  _check_covariances(gaussians.means.shape[0], covariances, view_rotations)
  return render_image_async(
    gaussians, camera, background=background, covariances=covariances,
    view_rotations=view_rotations, colors=colors, config=config,
    differentiable=differentiable, max_retries=max_retries).result()
