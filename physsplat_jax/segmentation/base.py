"""The result of segmentation: per-Gaussian object ids plus object names.

Segmentation runs on the host (NumPy/SciPy): its output sizes depend on the
data, and nothing in it is differentiated. :meth:`Segmentation.to_scene`
turns a result into a :class:`~physsplat_jax.types.Scene`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from physsplat_jax.errors import PhysSplatError
from physsplat_jax.types import Gaussians
from physsplat_jax.types import ObjectInfo
from physsplat_jax.types import Scene

BACKGROUND = -1


class SegmentationError(PhysSplatError, ValueError):
  """A segmentation that cannot be made or does not fit its scene (unknown
  method, missing inputs, ids or names that do not match); the message
  says which."""


@dataclasses.dataclass(frozen=True, eq=False)
class Segmentation:
  """Object ids of K Gaussians.

  Attributes:
    object_ids: (K,) int32 NumPy array; ``-1`` is background (not simulated).
    names: one name per object (index = object id).
    fixed: per object, True for supports that do not move (e.g. the table
      found by the plane fit); empty means all False.
    method: how it was made ('attribute', 'boxes', 'geometric', 'masks').
  """

  object_ids: np.ndarray
  names: tuple[str, ...]
  fixed: tuple[bool, ...] = ()
  method: str = ''

  def __post_init__(self):
    ids = np.asarray(self.object_ids)
    if ids.ndim != 1:
      raise SegmentationError(f'object_ids must be (K,), got shape {ids.shape}')
    n = len(self.names)
    if ids.size and (ids.min() < BACKGROUND or ids.max() >= n):
      raise SegmentationError(
        f'object_ids span [{ids.min()}, {ids.max()}] but there are {n} '
        'names; ids must be -1 (background) or in [0, len(names))')
    if self.fixed and len(self.fixed) != n:
      raise SegmentationError(
        f'fixed has {len(self.fixed)} entries for {n} objects')
    object.__setattr__(self, 'object_ids', ids.astype(np.int32))
    object.__setattr__(self, 'names', tuple(str(x) for x in self.names))
    object.__setattr__(self, 'fixed', tuple(bool(x) for x in self.fixed))

  @property
  def num_objects(self) -> int:
    return len(self.names)

  def counts(self) -> np.ndarray:
    """(num_objects,) Gaussians per object."""
    ids = self.object_ids[self.object_ids >= 0]
    return np.bincount(ids, minlength=self.num_objects)

  def objects(self, materials: Sequence[str | None] | None = None
              ) -> tuple[ObjectInfo, ...]:
    """ObjectInfo per object (tags carry the method)."""
    mats = materials or (None,) * self.num_objects
    fixed = self.fixed or (False,) * self.num_objects
    tags = (self.method,) if self.method else ()
    return tuple(ObjectInfo(name=n, material=m, fixed=f, tags=tags)
                 for n, m, f in zip(self.names, mats, fixed))

  def to_scene(self, gaussians: Gaussians, cameras=(), up_axis: str = 'z',
               meters_per_unit: float = 1.0, name: str = '',
               materials: Sequence[str | None] | None = None) -> Scene:
    """A :class:`Scene` with these ids and ObjectInfo entries."""
    if gaussians.num != self.object_ids.shape[0]:
      raise SegmentationError(
        f'segmentation has {self.object_ids.shape[0]} ids for '
        f'{gaussians.num} Gaussians')
    return Scene(
      gaussians=gaussians, object_ids=jnp.asarray(self.object_ids),
      objects=self.objects(materials), cameras=tuple(cameras),
      up_axis=up_axis, meters_per_unit=meters_per_unit, name=name)


def compact_labels(labels: np.ndarray, order: str = 'size'
                   ) -> tuple[np.ndarray, np.ndarray]:
  """Relabels non-negative labels to 0..n-1.

  Args:
    labels: (K,) ints; negative means background and stays -1.
    order: 'size' (largest first) or 'value' (ascending original label).

  Returns:
    (new labels (K,) int32, original label of each new id (n,)).
  """
  labels = np.asarray(labels)
  fg = labels >= 0
  uniq, inv, cnt = np.unique(labels[fg], return_inverse=True,
                             return_counts=True)
  if order == 'size':
    rank = np.argsort(-cnt, kind='stable')
  elif order == 'value':
    rank = np.arange(uniq.size)
  else:
    raise SegmentationError(f"order must be 'size' or 'value', got {order!r}")
  new_of_old = np.empty(uniq.size, np.int64)
  new_of_old[rank] = np.arange(uniq.size)
  out = np.full(labels.shape, BACKGROUND, np.int32)
  out[fg] = new_of_old[inv]
  return out, uniq[rank]
