"""Objects from per-Gaussian PLY properties (``object_id``, ``label``, ...).

3DGS exporters that segment (Gaussian Grouping, SAGA, Feature 3DGS
post-processing, hand-labelled SuperSplat files) store an integer per
vertex; :func:`physsplat_jax.io.ply.load_ply` keeps such properties in
``Gaussians.extras``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from physsplat_jax.segmentation.base import Segmentation
from physsplat_jax.segmentation.base import SegmentationError
from physsplat_jax.segmentation.base import compact_labels
from physsplat_jax.types import Gaussians
from physsplat_jax.io.scene import ID_PROPERTIES

# Property names recognised, in order of preference: the scene loader's.
ATTRIBUTE_KEYS = ID_PROPERTIES


def find_attribute(gaussians: Gaussians) -> str | None:
  """The first known object-id property in ``gaussians.extras``, or None."""
  low = {k.lower(): k for k in gaussians.extras}
  for k in ATTRIBUTE_KEYS:
    if k in low:
      return low[k]
  return None


def segment_by_attribute(
  gaussians: Gaussians,
  key: str | None = None,
  names: Mapping[int, str] | Sequence[str] | None = None,
  background_values: Sequence[int] = (),
) -> Segmentation:
  """Objects from an integer per-Gaussian property.

  Each distinct value becomes an object (ascending value order); negative
  values and ``background_values`` are background (-1).

  Args:
    gaussians: Gaussians whose ``extras`` hold the property.
    key: the property name; None picks the first of ``ATTRIBUTE_KEYS``.
    names: object names by label value (mapping) or by position in the
      sorted distinct values (sequence); default ``'object_<value>'``.
    background_values: label values meaning "no object" (e.g. ``(0,)``).

  Returns:
    A :class:`Segmentation` (method 'attribute').

  Raises:
    ValueError: no such property, or non-integer values (the message names
      the property and a bad value).
  """
  if key is None:
    key = find_attribute(gaussians)
    if key is None:
      raise SegmentationError(
        'no object-id property in the Gaussians (PLY extras are '
        f'{sorted(gaussians.extras)}); expected one of {list(ATTRIBUTE_KEYS)}'
        ' or pass key=')
  if key not in gaussians.extras:
    raise SegmentationError(
      f'property {key!r} not in the Gaussians; extras are '
      f'{sorted(gaussians.extras)}')
  raw = np.asarray(gaussians.extras[key])
  if raw.shape != (gaussians.num,):
    raise SegmentationError(f'property {key!r} has shape {raw.shape}, expected '
                            f'({gaussians.num},)')
  if np.issubdtype(raw.dtype, np.floating):
    if not np.all(np.isfinite(raw)):
      raise SegmentationError(f'property {key!r} has non-finite values')
    bad = np.abs(raw - np.round(raw)) > 1e-3
    if bad.any():
      i = int(np.argmax(bad))
      raise SegmentationError(
        f'property {key!r} is not an integer label (row {i}: '
        f'{raw[i]}); pass key= naming an id property')
    raw = np.round(raw)
  labels = raw.astype(np.int64)
  for b in background_values:
    labels = np.where(labels == b, -1, labels)
  ids, values = compact_labels(labels, order='value')
  if names is None:
    out_names = [f'object_{v}' for v in values]
  elif isinstance(names, Mapping):
    by_value = {}
    for k, name in names.items():
      try:  # JSON keys are strings: {'3': 'cup'} means label 3
        value = int(k)
        ok = float(k) == value and not isinstance(k, bool)
      except (TypeError, ValueError):
        ok = False
      if not ok:
        raise SegmentationError(
          f'names: key {k!r} is not a label value; key the names by the '
          f"integer labels of property {key!r} ({list(values)[:8]}...)")
      by_value[value] = str(name)
    unused = sorted(set(by_value) - {int(v) for v in values})
    if unused:
      raise SegmentationError(
        f'names: label(s) {unused} do not occur in property {key!r} '
        f'(its labels are {list(values)}; background ones removed)')
    out_names = [by_value.get(int(v), f'object_{v}') for v in values]
  else:
    if isinstance(names, (str, bytes)):
      raise SegmentationError(
        f'names={names!r}: give a list of names (one per label) or a '
        'mapping label -> name, not one string')
    names = [str(n) for n in names]
    if len(names) != len(values):
      raise SegmentationError(f'{len(names)} names for {len(values)} distinct '
                              f'labels {list(values)}')
    out_names = names
  return Segmentation(ids, tuple(out_names), method='attribute')
