"""Objects from axis-aligned boxes (PhysGaussian ``sim_area``).

A box is ``(xmin, xmax, ymin, ymax, zmin, zmax)`` in the frame where it was
drawn; PhysGaussian tests ``sim_area`` after its preprocessing rotation, so a
``rotation`` can be applied to the centres first. A Gaussian inside several
boxes goes to the smallest (nested boxes: a pot box inside a plant box);
inside none, to the background.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from absl import logging

from physsplat_jax.segmentation.base import Segmentation
from physsplat_jax.segmentation.base import SegmentationError
from physsplat_jax.types import Gaussians


def _as_boxes(boxes) -> np.ndarray:
  try:
    b = np.asarray(boxes, np.float64)
  except (TypeError, ValueError) as e:
    raise SegmentationError(
      f'boxes must be numbers, (n, 6) as (xmin, xmax, ymin, ymax, zmin, '
      f'zmax), got {boxes!r} ({e})') from None
  if b.ndim == 1:
    b = b[None]
  if b.ndim != 2 or b.shape[1] != 6:
    raise SegmentationError(f'boxes must be (n, 6) as (xmin, xmax, ymin, ymax, '
                            f'zmin, zmax), got shape {b.shape}')
  if not np.all(np.isfinite(b)):
    raise SegmentationError('boxes contain non-finite values')
  bad = np.nonzero(np.any(b[:, 1::2] < b[:, 0::2], axis=1))[0]
  if bad.size:
    raise SegmentationError(
      f'box {int(bad[0])} = {b[bad[0]].tolist()} has a max '
      'below its min; order is (xmin, xmax, ymin, ymax, zmin, '
      'zmax)')
  return b


def _rotated(means, rotation) -> np.ndarray:
  """(K, 3) float64 centres, times ``rotation``^T when one is given (a
  finite 3x3 orthonormal matrix, checked)."""
  x = np.asarray(means, np.float64)
  if rotation is None:
    return x
  try:
    r = np.asarray(rotation, np.float64)
  except (TypeError, ValueError) as e:
    raise SegmentationError(f'rotation must be a 3x3 matrix of numbers ({e})'
                            ) from None
  if r.shape != (3, 3) or not np.all(np.isfinite(r)) or not np.allclose(
      r @ r.T, np.eye(3), atol=1e-4):
    raise SegmentationError(
      f'rotation must be a finite 3x3 rotation matrix (R R^T = I), got '
      f'{np.round(r, 6).tolist()}; build it with '
      'scipy.spatial.transform.Rotation(...).as_matrix()')
  return x @ r.T


def inside_box(means, box, rotation=None, strict: bool = False
               ) -> np.ndarray:
  """(K,) bool: centres inside ``box`` = (xmin, xmax, ymin, ymax, zmin,
  zmax), after ``rotation`` (3, 3) when given; ``strict`` excludes the
  faces (PhysGaussian's ``sim_area`` test), else they are inside."""
  x = _rotated(means, rotation)
  b = _as_boxes(box)[0]
  if strict:
    return np.all((x > b[0::2]) & (x < b[1::2]), axis=1)
  return np.all((x >= b[0::2]) & (x <= b[1::2]), axis=1)


def box_labels(means, boxes, rotation=None) -> np.ndarray:
  """(K,) index of the smallest containing box (inclusive), -1 for none."""
  x = _rotated(means, rotation)
  b = _as_boxes(boxes)
  vol = np.prod(b[:, 1::2] - b[:, 0::2], axis=1)
  out = np.full(x.shape[0], -1, np.int32)
  best = np.full(x.shape[0], np.inf)
  for i in np.argsort(vol, kind='stable'):
    inside = inside_box(x, b[i])
    take = inside & (vol[i] < best)
    out[take] = i
    best[take] = vol[i]
  return out


def segment_by_boxes(
  gaussians: Gaussians,
  boxes,
  names: Sequence[str] | None = None,
  rotation=None,
  fixed: Sequence[bool] | None = None,
) -> Segmentation:
  """One object per box.

  Args:
    gaussians: the Gaussians (their means are tested).
    boxes: (n, 6) ``(xmin, xmax, ymin, ymax, zmin, zmax)``, or one box.
    names: n names (default ``'box_<i>'``).
    rotation: (3, 3) applied to the means before the test (PhysGaussian
      ``rotation_degree``/``rotation_axis``).
    fixed: n flags for objects that do not move.

  Returns:
    A :class:`Segmentation` (method 'boxes'); empty boxes still name an
    object (with no Gaussians), and a warning names each one.
  """
  b = _as_boxes(boxes)
  n = b.shape[0]
  names = tuple(names) if names is not None else tuple(
    f'box_{i}' for i in range(n))
  if len(names) != n:
    raise SegmentationError(f'{len(names)} names for {n} boxes')
  ids = box_labels(gaussians.means, b, rotation)
  counts = np.bincount(ids[ids >= 0], minlength=n)
  for i in np.flatnonzero(counts == 0):
    logging.warning(
      'segment_by_boxes: box %d (%s) = %s holds no Gaussian centre (they '
      'span %s); its object is empty. Order is (xmin, xmax, ymin, ymax, '
      'zmin, zmax)%s.', i, names[i], b[i].tolist(),
      _span(gaussians.means, rotation),
      ', after the rotation' if rotation is not None else '')
  return Segmentation(ids, names, tuple(fixed or ()), method='boxes')


def _span(means, rotation) -> list:
  x = _rotated(means, rotation)
  if not len(x):
    return []
  return np.round(np.stack([x.min(0), x.max(0)], 1).ravel(), 4).tolist()
