"""One entry point that picks a segmentation method."""

from __future__ import annotations

import inspect
from collections.abc import Sequence

from physsplat_jax.segmentation.attributes import find_attribute
from physsplat_jax.segmentation.attributes import segment_by_attribute
from physsplat_jax.segmentation.base import Segmentation
from physsplat_jax.segmentation.base import SegmentationError
from physsplat_jax.segmentation.boxes import segment_by_boxes
from physsplat_jax.segmentation.geometric import segment_geometric
from physsplat_jax.segmentation.masks import lift_masks
from physsplat_jax.types import Gaussians

METHODS = ('auto', 'attribute', 'boxes', 'masks', 'geometric')

_FUNCTIONS = dict(attribute=segment_by_attribute, boxes=segment_by_boxes,
                  masks=lift_masks, geometric=segment_geometric)
_WHY = dict(boxes='boxes= was given', masks='masks= was given',
            attribute='the Gaussians carry an object-id property',
            geometric='nothing else was given')


def _check_options(method: str, kwargs, asked: str) -> None:
  """Refuses options that the method's function does not take (a
  TypeError from deep inside before), naming the method that takes them."""
  params = inspect.signature(_FUNCTIONS[method]).parameters
  taken = {n for n, p in params.items()
           if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)}
  bad = sorted(set(kwargs) - taken)
  if not bad:
    return
  owners = sorted(m for m, fn in _FUNCTIONS.items()
                  if set(bad) <= set(inspect.signature(fn).parameters))
  why = (f"'auto' chose '{method}' because {_WHY[method]}"
         if asked == 'auto' else f"method '{method}'")
  hint = (f"; pass method='{owners[0]}' for them" if owners else '')
  raise SegmentationError(
    f'segment: option(s) {bad} do not apply: {why}, which takes '
    f'{sorted(taken - {"gaussians", "names", "boxes", "cameras", "masks"})}'
    f'{hint}')


def segment(
  gaussians: Gaussians,
  method: str = 'auto',
  *,
  names: Sequence[str] | None = None,
  boxes=None,
  cameras=None,
  masks=None,
  up=(0.0, 0.0, 1.0),
  **kwargs,
) -> Segmentation:
  """Segments with the given method, or the best available one.

  'auto' uses, in order: ``boxes`` if given, ``masks`` (with ``cameras``)
  if given, an object-id PLY property if present, else the geometric
  method (what the caller passes wins over what the file carries).

  Args:
    gaussians: the scene's Gaussians.
    method: one of ``METHODS``.
    names: object names for the chosen method (optional).
    boxes: (n, 6) boxes for 'boxes'.
    cameras, masks: views and label masks for 'masks'.
    up: world up for 'geometric'.
    **kwargs: passed to the method's function.

  Returns:
    A :class:`Segmentation`.
  """
  if method not in METHODS:
    raise SegmentationError(f'segmentation method {method!r} is not one of '
                            f'{METHODS}')
  if method == 'auto':
    if boxes is not None:
      method = 'boxes'
    elif masks is not None:
      method = 'masks'
    elif find_attribute(gaussians) is not None:
      method = 'attribute'
    else:
      method = 'geometric'
    _check_options(method, kwargs, 'auto')
  else:
    _check_options(method, kwargs, method)
  if method == 'attribute':
    return segment_by_attribute(gaussians, names=names, **kwargs)
  if method == 'boxes':
    if boxes is None:
      raise SegmentationError("segmentation method 'boxes' needs boxes=")
    return segment_by_boxes(gaussians, boxes, names=names, **kwargs)
  if method == 'masks':
    if masks is None or cameras is None:
      raise SegmentationError(
        "segmentation method 'masks' needs cameras= and masks=")
    return lift_masks(gaussians, cameras, masks, names=names, **kwargs)
  seg = segment_geometric(gaussians, up=up, **kwargs)
  if names is not None:
    if len(names) != seg.num_objects:
      raise SegmentationError(
        f'{len(names)} names for {seg.num_objects} objects found '
        f'({seg.names})')
    seg = Segmentation(seg.object_ids, tuple(names), seg.fixed, seg.method)
  return seg
