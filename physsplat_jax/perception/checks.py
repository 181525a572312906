"""Checks of what callers hand to perception (options, views).

Each check raises :class:`PerceptionError` naming the field or argument,
the value and what is allowed, before any question is asked.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from physsplat_jax.errors import PhysSplatError
from physsplat_jax.values import is_int, is_number


class PerceptionError(PhysSplatError, ValueError):
  """Bad perception options, or an object that cannot be perceived; the
  message names the field or the object."""


def bad_option(field: str, value, want: str):
  """Raises the error of a bad ``PerceptionOptions.<field>``."""
  raise PerceptionError(f'PerceptionOptions.{field} must be {want}, got '
                        f'{value!r}')


def number(v) -> float | None:
  """``v`` as a float when it is a real number (not a bool, not NaN), else
  None."""
  return float(v) if is_number(v) and not math.isnan(v) else None


def numbers(v, n: int) -> list[float] | None:
  """``v`` as ``n`` finite numbers, or None."""
  if not isinstance(v, (Sequence, np.ndarray)) or isinstance(
      v, (str, bytes)) or len(v) != n:
    return None
  out = [number(x) for x in v]
  return out if all(x is not None and math.isfinite(x) for x in out) else None


VIEW_FORM = ('an (H, W, 3) or (H, W, 4) image (uint8, or floats in '
             '[0, 1]), or a non-empty sequence of them')


def views_of(image, where: str) -> list[np.ndarray]:
  """The views of one object given by a caller, as arrays.

  Args:
    image: one (H, W, 3|4) view or a sequence of them.
    where: the argument's name for messages (``'images[0]'``).

  Raises:
    PerceptionError: not such a view (names ``where`` and the shape).
  """
  try:
    nd = np.ndim(image)
  except ValueError:  # ragged: views of different sizes
    nd = None
  views = [image] if nd == 3 else (
    list(image) if nd in (4, None) or isinstance(image, (list, tuple))
    else None)
  if not views:
    got = f'shape {np.shape(image)}' if nd is not None else type(
      image).__name__
    raise PerceptionError(f'{where}: expected {VIEW_FORM}, got {got}')
  out = []
  for j, v in enumerate(views):
    name = where if nd == 3 else f'{where}[{j}]'
    try:
      a = np.asarray(v)
    except ValueError:
      a = np.asarray(None)
    if a.ndim != 3 or a.shape[2] not in (3, 4) or 0 in a.shape[:2] or not (
        np.issubdtype(a.dtype, np.number) or a.dtype == bool):
      raise PerceptionError(f'{name}: expected {VIEW_FORM}, got shape '
                            f'{a.shape} ({a.dtype})')
    out.append(a)
  return out


def check_images(images, names: Sequence[str],
                 scene_name: str = '') -> dict[int, list[np.ndarray]]:
  """``perceive_scene``'s ``images`` as object index -> views.

  Args:
    images: None, or a mapping object index -> view(s).
    names: the scene's object names.
    scene_name: for messages.

  Raises:
    PerceptionError: not a mapping, an index that names no object (with
      the valid range) or a bad view (``images[i]`` and its shape).
  """
  if images is None:
    return {}
  n = len(names)
  if not isinstance(images, Mapping):
    raise PerceptionError(f'images must map an object index (0..{n - 1}) '
                          f'to its view(s), got {type(images).__name__}')
  out = {}
  for i, v in images.items():
    if not (is_int(i) and 0 <= i < n):
      raise PerceptionError(
        f'images[{i!r}]: no such object; scene {scene_name!r} has {n} '
        f'object(s), indices 0..{n - 1} ({list(names)})')
    out[int(i)] = views_of(v, f'images[{i}]')
  return out
