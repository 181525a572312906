"""Space-time slices: one line of pixels stacked over time into an image.

PhysDreamer (Zhang et al., ECCV 2024) compares motion this way: take the same
line of pixels (a row, a column, or a segment between two pixel points) in
every frame of a video and stack the lines, so that one axis of the slice is
position along the line and the other is time. A still region gives straight
streaks, an oscillation gives a wave, a fall gives a curve, and two
simulations with different materials are easy to compare side by side.

Pixel coordinates: ``(x, y) = (column, row)`` indices, pixel ``(i, j)`` at
``(x, y) = (j, i)``. A segment is sampled at ``num_samples`` equally spaced
points (default one per pixel of length) with bilinear interpolation, so a
horizontal segment between integer points reproduces the row exactly.

All functions are pure (NumPy or JAX arrays in, JAX arrays out); see
:func:`physsplat_jax.io.video.save_space_time_slice` writes one as PNG.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from physsplat_jax.render.config import RenderInputError
from physsplat_jax.types import Array


def _check_frames(frames) -> Array:
  frames = jnp.asarray(frames)
  if frames.ndim != 4 or frames.shape[0] < 1:
    raise RenderInputError(
      f'space_time_slice: frames have shape {frames.shape}; expected '
      '(T, H, W, C) with T >= 1'
    )
  return frames


def line_points(
  start, end, num_samples: int | None = None
) -> np.ndarray:
  """Sample points of a segment in pixel coordinates.

  Args:
    start, end: (x, y) = (column, row) pixel coordinates (floats allowed).
    num_samples: points along the segment, ends included (default:
      ``ceil(length) + 1``, about one per pixel).

  Returns:
    (L, 2) float64 (x, y) points from ``start`` to ``end``.
  """
  p0 = np.asarray(start, np.float64)
  p1 = np.asarray(end, np.float64)
  if p0.shape != (2,) or p1.shape != (2,):
    raise RenderInputError(
      f'line_points: start and end must be (x, y) pairs, got {p0.shape} and '
      f'{p1.shape}'
    )
  if not (np.all(np.isfinite(p0)) and np.all(np.isfinite(p1))):
    raise RenderInputError(f'line_points: non-finite points {p0}, {p1}')
  if num_samples is None:
    num_samples = int(math.ceil(float(np.linalg.norm(p1 - p0)))) + 1
  if int(num_samples) < 2:
    raise RenderInputError(f'line_points: num_samples must be >= 2, got '
                           f'{num_samples}')
  s = np.linspace(0.0, 1.0, int(num_samples))[:, None]
  return p0 + s * (p1 - p0)


def sample_bilinear(frames: Array, points) -> Array:
  """Bilinear samples of (T, H, W, C) frames at (L, 2) (x, y) points.

  Points are clamped to the image (edge pixels repeat outside it).

  Returns:
    (T, L, C) samples.
  """
  frames = _check_frames(frames)
  _, H, W, _ = frames.shape
  pts = jnp.asarray(points, frames.dtype if jnp.issubdtype(
    frames.dtype, jnp.floating) else jnp.float32)
  x = jnp.clip(pts[:, 0], 0.0, W - 1.0)
  y = jnp.clip(pts[:, 1], 0.0, H - 1.0)
  x0 = jnp.clip(jnp.floor(x).astype(jnp.int32), 0, max(W - 2, 0))
  y0 = jnp.clip(jnp.floor(y).astype(jnp.int32), 0, max(H - 2, 0))
  x1 = jnp.minimum(x0 + 1, W - 1)
  y1 = jnp.minimum(y0 + 1, H - 1)
  fx = (x - x0)[None, :, None]
  fy = (y - y0)[None, :, None]
  f = frames.astype(fx.dtype)
  top = f[:, y0, x0] * (1 - fx) + f[:, y0, x1] * fx
  bot = f[:, y1, x0] * (1 - fx) + f[:, y1, x1] * fx
  return top * (1 - fy) + bot * fy


def space_time_slice(
  frames,
  *,
  row: int | None = None,
  column: int | None = None,
  start=None,
  end=None,
  num_samples: int | None = None,
  time_axis: int = 0,
) -> Array:
  """Stacks one line of pixels over time (PhysDreamer's space-time slice).

  Give exactly one of ``row``, ``column`` or ``start``/``end``.

  Args:
    frames: (T, H, W, C) video (float or integer).
    row: take pixel row ``row`` (a horizontal line, length W).
    column: take pixel column ``column`` (a vertical line, length H).
    start, end: (x, y) = (column, row) ends of a segment (bilinear samples).
    num_samples: samples along the segment (see :func:`line_points`).
    time_axis: 0: result (T, L, C), time running down the image;
      1: result (L, T, C), time running to the right.

  Returns:
    The slice, (T, L, C) or (L, T, C); rows/columns keep the frames' dtype,
    segments are float.

  Raises:
    ValueError: no line or several, indices out of range, bad shapes.
  """
  frames = _check_frames(frames)
  _, H, W, _ = frames.shape
  given = [row is not None, column is not None,
           start is not None or end is not None]
  if sum(given) != 1:
    raise RenderInputError(
      'space_time_slice: give exactly one of row=, column= or start=/end='
    )
  if time_axis not in (0, 1):
    raise RenderInputError(
      f'space_time_slice: time_axis must be 0 or 1, got {time_axis}')
  if row is not None:
    if not 0 <= int(row) < H:
      raise RenderInputError(f'space_time_slice: row {row} outside 0..{H - 1}')
    out = frames[:, int(row)]
  elif column is not None:
    if not 0 <= int(column) < W:
      raise RenderInputError(
        f'space_time_slice: column {column} outside 0..{W - 1}')
    out = frames[:, :, int(column)]
  else:
    if start is None or end is None:
      raise RenderInputError('space_time_slice: give both start= and end=')
    out = sample_bilinear(frames, line_points(start, end, num_samples))
  return out if time_axis == 0 else jnp.swapaxes(out, 0, 1)


def draw_line(image, *, row=None, column=None, start=None, end=None,
              color=(1.0, 0.0, 0.0)) -> Array:
  """Marks a slice's line on one (H, W, 3) float image (for figures).

  Same line arguments as :func:`space_time_slice`; returns a copy with the
  line's pixels (nearest pixel of each sample) set to ``color``.
  """
  image = jnp.asarray(image)
  if image.ndim != 3:
    raise RenderInputError(
      f'draw_line: image has shape {image.shape}; expected (H, W, C)')
  H, W, _ = image.shape
  color = jnp.asarray(color, image.dtype)
  if row is not None:
    return image.at[int(row)].set(color)
  if column is not None:
    return image.at[:, int(column)].set(color)
  pts = np.round(line_points(start, end)).astype(np.int64)
  x = np.clip(pts[:, 0], 0, W - 1)
  y = np.clip(pts[:, 1], 0, H - 1)
  return image.at[y, x].set(color)
