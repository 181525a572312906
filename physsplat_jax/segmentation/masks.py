"""2D masks of several views lifted to per-Gaussian object ids.

Each Gaussian takes the visibility-weighted vote of the views. The weight
of Gaussian k for label l in one view is its compositing contribution summed
over the pixels that the view's mask gives label l::

  W_v[k, l] = sum_{p : mask_v(p) = l} alpha_k(p) T_k(p)

(``alpha_k(p) T_k(p)`` is exactly the weight of k's colour in pixel p, so
an occluded Gaussian's say shrinks with the transmittance in front of it,
and a Gaussian seen across a mask border splits its vote by area). A view
counts in proportion to the pixels a Gaussian covers there: closer or
higher-resolution views weigh more. The renderer is linear in the
per-Gaussian colours ``c``: ``image(p) = sum_k c_k alpha_k(p) T_k(p)``
with a black background, so ``W_v[:, l]`` is the vector-Jacobian product
of the image with the one-hot image of label l -- one reverse pass of
:func:`~physsplat_jax.render.render_differentiable` per three labels (one
per colour channel), exact with the renderer's semantics (tiles, alpha cap,
early stop).

A view votes for Gaussian k only where k is visible in it: its visible
fraction ``sum_l W_v[k, l] / A_v[k]``, against its unoccluded weight
``A_v[k] = sum_p alpha_k(p)`` (:func:`unoccluded_weights`: the same
pass with every opacity, ``alpha_min`` and ``alpha_max`` scaled by 1e-4,
so that nothing occludes and the same pixels count), must reach
``min_visibility`` (5 %). The label of a pixel is that of the surface in
front, so a Gaussian seen only through an occluder (behind one opaque
layer it keeps under 1 % of its weight) would take the occluder's label:
a wall's id on the object behind it, a cup's on the table under it. With
the rule no view votes for it, and it is filled like an unseen Gaussian.

Votes are summed over views; pixels without a label (-1) vote for
"unlabelled". Gaussian k gets ``argmax_l sum_v W_v[k, l]`` if that beats its
unlabelled weight, else background (-1). Gaussians seen in no view (total
weight of the views that vote for them below ``min_weight``: the inside of
an object, what only an occluder shows) take the id of the nearest decided
Gaussian (``fill_unseen='nearest'``) or stay background.
Labels must be consistent across views (the same object has the same id in
every mask, e.g. SAM masks with a tracker or hand-matched ids).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
import scipy
from absl import logging

from physsplat_jax.render import RenderCapacityError
from physsplat_jax.render import RenderConfig
from physsplat_jax.render import fit_render_config
from physsplat_jax.render import render_differentiable
from physsplat_jax.segmentation.base import BACKGROUND
from physsplat_jax.segmentation.base import Segmentation
from physsplat_jax.segmentation.base import SegmentationError
from physsplat_jax.types import Camera
from physsplat_jax.types import Gaussians


@functools.partial(jax.jit, static_argnames=('config',))
def _weights_jit(gaussians, camera, cotangents, config):
  K = gaussians.means.shape[0]

  def image(colors):
    out = render_differentiable(gaussians, camera, colors=colors,
                                config=config)
    return out.image, out.overflow

  colors0 = jnp.zeros((K, 3), gaussians.means.dtype)
  _, vjp_fn, overflow = jax.vjp(image, colors0, has_aux=True)
  w = jax.lax.map(lambda c: vjp_fn(c)[0], cotangents)  # (G, K, 3)
  return w, overflow


def shared_render_config(gaussians: Gaussians, cameras: Sequence[Camera],
                         config: RenderConfig | None = None) -> RenderConfig:
  """One differentiable-path config that fits every view (one compile)."""
  config = config or RenderConfig()
  cap, chunks = 1024, 1
  for cam in cameras:
    c = fit_render_config(gaussians, cam.unlabelled(), config)
    cap, chunks = max(cap, c.capacity), max(chunks, c.max_chunks)
  return dataclasses.replace(config, capacity=cap, max_chunks=chunks)


def contribution_weights(
  gaussians: Gaussians,
  camera: Camera,
  labels,
  num_labels: int,
  config: RenderConfig | None = None,
) -> np.ndarray:
  """Per-Gaussian compositing weight inside each label of one mask.

  Args:
    gaussians: K Gaussians.
    camera: the view (its size must match the mask).
    labels: (H, W) ints; ``0 <= l < num_labels`` are objects, anything else
      is "unlabelled".
    num_labels: L.
    config: renderer settings; capacity and chunks are sized here unless
      both are set (see :func:`shared_render_config`).

  Returns:
    (K, L + 1) float64 ``W[k, l] = sum_{mask = l} alpha_k T_k``; column L is
    the unlabelled pixels.
  """
  lab = np.asarray(labels)
  H, W = camera.height, camera.width
  if lab.shape != (H, W):
    raise SegmentationError(
      f'mask shape {lab.shape} != camera size ({H}, {W}); '
      'resize the camera with Camera.resized(W, H)')
  L = int(num_labels)
  cols = np.where((lab >= 0) & (lab < L), lab, L)
  G = -(-(L + 1) // 3)
  onehot = np.zeros((G * 3, H, W), np.float32)
  onehot[cols, np.arange(H)[:, None], np.arange(W)[None, :]] = 1.0
  cot = onehot.reshape(G, 3, H, W).transpose(0, 2, 3, 1)
  w = _vjp_weights(gaussians, camera, cot, config)
  return w.transpose(1, 0, 2).reshape(-1, G * 3)[:, :L + 1]


# Opacities and alpha bounds scaled by this make every transmittance
# 1 - O(_UNOCCLUDED_SCALE * depth complexity) with the same pixels drawn.
_UNOCCLUDED_SCALE = 1e-4


def unoccluded_weights(
  gaussians: Gaussians,
  camera: Camera,
  config: RenderConfig | None = None,
) -> np.ndarray:
  """Each Gaussian's weight in a view as if nothing were in front of it.

  ``A[k] = sum_p alpha_k(p)`` over the pixels the renderer draws k in
  (alpha cap, ``alpha_min``, tiles), with every transmittance 1. Against
  :func:`contribution_weights` summed over labels (the same sum with the
  transmittance ``T_k(p)``) it gives the fraction of k that the view sees.
  Computed as the reverse pass of an image in which every opacity and
  both alpha bounds are scaled by 1e-4: the same pixels are drawn and each
  transmittance is ``1 - O(1e-4)`` per Gaussian in front.

  Args:
    gaussians: K Gaussians.
    camera: the view.
    config: renderer settings (as :func:`contribution_weights`).

  Returns:
    (K,) float64, 0 for Gaussians the view does not draw.
  """
  eps = _UNOCCLUDED_SCALE
  dtype = gaussians.opacity_logits.dtype
  log_o = jnp.log(eps) + jax.nn.log_sigmoid(gaussians.opacity_logits)
  logits = (log_o - jnp.log1p(-jnp.exp(log_o))).astype(dtype)
  faint = gaussians.replace(opacity_logits=logits)
  config = config or RenderConfig()
  if config.capacity is None or config.max_chunks is None:
    config = fit_render_config(gaussians, camera.unlabelled(), config)
  config = dataclasses.replace(config, alpha_min=config.alpha_min * eps,
                               alpha_max=config.alpha_max * eps)
  cot = np.ones((1, camera.height, camera.width, 3), np.float32)
  return _vjp_weights(faint, camera, cot, config)[0, :, 0] / eps


def _vjp_weights(gaussians, camera, cot, config) -> np.ndarray:
  """(G, K, 3) reverse passes of the colours for G (H, W, 3) cotangents,
  the render's capacity grown until it does not overflow."""
  cot = jnp.asarray(cot, gaussians.means.dtype)
  camera = camera.unlabelled()
  config = config or RenderConfig()
  if config.capacity is None or config.max_chunks is None:
    config = fit_render_config(gaussians, camera, config)
  for _ in range(4):
    w, overflow = _weights_jit(gaussians, camera, cot, config)
    if not bool(overflow):
      return np.asarray(w, np.float64)
    config = fit_render_config(gaussians, camera, config, margin=2.0)
  raise RenderCapacityError(
    'contribution_weights: the renderer kept overflowing its tile lists '
    'after growing them 4 times; pass a RenderConfig with a larger '
    'capacity and max_chunks (render.fit_render_config(..., margin=4))')


def _check_aspect(i: int, cam: Camera, shape) -> None:
  """Refuses a mask whose aspect ratio is not the camera's: resizing the
  camera to it would stretch the image (a transposed (W, H) mask labelled
  the wrong Gaussians silently). Rounding of a downscaled mask is allowed
  (one pixel)."""
  H, W = cam.height, cam.width
  h, w = shape
  if abs(W * h / H - w) <= 1 or abs(H * w / W - h) <= 1:
    return
  hint = ' (transposed? masks are (H, W) = (rows, columns))' if (
    (h, w) == (W, H)) else ''
  raise SegmentationError(
    f'mask {i} is {h}x{w} (H x W) but camera {i} is {H}x{W}: another '
    f'aspect ratio{hint}. Give a mask of the camera\'s shape, or a '
    'uniformly resized one; for another image size pass '
    'camera.resized(W, H)')


def lift_masks(
  gaussians: Gaussians,
  cameras: Sequence[Camera],
  masks: Sequence,
  names: Sequence[str] | None = None,
  num_labels: int | None = None,
  min_weight: float = 1e-3,
  min_visibility: float = 0.05,
  fill_unseen: str = 'nearest',
  config: RenderConfig | None = None,
) -> Segmentation:
  """Object ids from label masks of several views (module docstring).

  Args:
    gaussians: K Gaussians.
    cameras: V cameras; a camera whose size differs from its mask is
      resized to the mask when the aspect ratios agree (to a pixel), else
      a SegmentationError (a transposed mask).
    masks: V (H, W) int label images (-1 = no object).
    names: object names by label (default ``'object_<l>'``).
    num_labels: L (default: largest label + 1, or ``len(names)`` if more).
    min_weight: a Gaussian whose summed weight over the views that vote for
      it is below this counts as unseen.
    min_visibility: a view votes for a Gaussian only if this fraction of
      its unoccluded weight reaches the image there (module doc); 0 lets
      every view vote, so that what is seen only through an occluder
      takes the occluder's label.
    fill_unseen: 'nearest' (id of the nearest decided Gaussian) or
      'background'.
    config: renderer settings.

  Returns:
    A :class:`Segmentation` (method 'masks').
  """
  if len(cameras) != len(masks) or len(masks) == 0:  # (V, H, W) arrays too
    raise SegmentationError(
      f'lift_masks: {len(cameras)} cameras for {len(masks)} '
      'masks; give one mask per camera (at least one)')
  if fill_unseen not in ('nearest', 'background'):
    raise SegmentationError(
      f"fill_unseen must be 'nearest' or 'background', got "
      f'{fill_unseen!r}')
  if not 0.0 <= min_visibility <= 1.0:
    raise SegmentationError(
      f'min_visibility={min_visibility!r} is a fraction of a Gaussian\'s '
      'weight that a view must see: give a value in [0, 1] (default 0.05; '
      '0 lets views vote through occluders)')
  for i, cam in enumerate(cameras):
    if not isinstance(cam, Camera):
      raise SegmentationError(
        f'lift_masks: cameras[{i}] is a {type(cam).__name__}, not a Camera; '
        'pass scene.cameras entries (or types.make_camera)')
  masks = [np.asarray(m) for m in masks]
  for i, m in enumerate(masks):
    if m.ndim != 2 or not np.issubdtype(m.dtype, np.integer):
      raise SegmentationError(
        f'mask {i} must be an (H, W) integer label image, got '
        f'{m.dtype} {m.shape}')
  if num_labels is None:
    for i, m in enumerate(masks):
      if (np.issubdtype(m.dtype, np.unsignedinteger)
          and m.max() == np.iinfo(m.dtype).max):
        raise SegmentationError(
          f'mask {i} ({m.dtype}) holds {int(m.max())}, its largest value: '
          'a "void" marker would make that many objects. Pass '
          'num_labels=L (labels >= L count as unlabelled), or mark '
          'unlabelled pixels -1 in a signed integer mask')
    num_labels = max(int(m.max()) for m in masks) + 1
    if names is not None:  # (an object in no mask keeps its name)
      num_labels = max(num_labels, len(names))
  L = max(int(num_labels), 1)
  for i, (cam, m) in enumerate(zip(cameras, masks)):
    _check_aspect(i, cam, m.shape)
  cameras = [
    cam if (cam.height, cam.width) == m.shape else cam.resized(
      m.shape[1], m.shape[0]) for cam, m in zip(cameras, masks)]
  config = shared_render_config(gaussians, cameras, config)
  total = np.zeros((gaussians.num, L + 1))
  seen_any = False
  for i, (cam, m) in enumerate(zip(cameras, masks)):
    if len(cameras) > 1:
      logging.info('lift_masks: view %d/%d (%dx%d)', i + 1, len(cameras),
                   m.shape[1], m.shape[0])
    w = contribution_weights(gaussians, cam, m, L, config)
    if not w.sum() > 0:
      logging.warning('lift_masks: camera %d sees none of the %d Gaussians '
                      '(its mask is ignored); check its pose', i,
                      gaussians.num)
      continue
    seen_any = True
    if min_visibility > 0:  # views vote only where they see the Gaussian
      full = unoccluded_weights(gaussians, cam, config)
      w = np.where((w.sum(1) >= min_visibility * full)[:, None], w, 0.0)
    total += w
  if gaussians.num and not seen_any:
    raise SegmentationError(
      f'lift_masks: none of the {len(cameras)} cameras sees any of the '
      f'{gaussians.num} Gaussians; check the cameras\' poses (world-to-'
      'camera viewmat) and near/far against the scene')
  obj = np.argmax(total[:, :L], axis=1)
  best = total[np.arange(gaussians.num), obj]
  seen = total.sum(1) >= min_weight
  ids = np.where(seen & (best > total[:, L]), obj, BACKGROUND).astype(np.int32)
  if fill_unseen == 'nearest' and (~seen).any() and seen.any():
    x = np.asarray(gaussians.means, np.float64)
    tree = scipy.spatial.cKDTree(x[seen])
    _, j = tree.query(x[~seen])
    ids[~seen] = ids[seen][j]
  if names is None:
    names = [f'object_{l}' for l in range(L)]
  names = tuple(names)
  if len(names) != L:
    raise SegmentationError(
      f'lift_masks: {len(names)} names for {L} labels (0..{L - 1}); give a '
      'name for each label the masks use')
  return Segmentation(ids, names, method='masks')


def masks_accuracy(pred, truth) -> float:
  """Fraction of equal ids (for tests and reports)."""
  pred, truth = np.asarray(pred), np.asarray(truth)
  return float(np.mean(pred == truth)) if pred.size else math.nan
