"""2D masks of several views lifted to per-Gaussian object ids.

Each Gaussian takes the visibility-weighted vote of the views. The weight
of Gaussian k for label l in one view is its compositing contribution summed
over the pixels that the view's mask gives label l::

  W_v[k, l] = sum_{p : mask_v(p) = l} alpha_k(p) T_k(p)

(``alpha_k(p) T_k(p)`` is exactly the weight of k's colour in pixel p, so
an occluded Gaussian's say shrinks with the transmittance in front of it,
and a Gaussian seen across a mask border splits its vote by area). Behind
one opaque layer (alpha capped at 0.99) a Gaussian keeps about 1 % of its
weight: a view that sees it outvotes the views that see it only through
an occluder, but a Gaussian seen in no view except through one takes the
occluder's label (raise ``min_weight`` to count it unseen instead). A view
counts in proportion to the pixels a Gaussian covers there: closer or
higher-resolution views weigh more. The renderer is linear in the
per-Gaussian colours ``c``: ``image(p) = sum_k c_k alpha_k(p) T_k(p)``
with a black background, so ``W_v[:, l]`` is the vector-Jacobian product
of the image with the one-hot image of label l -- one reverse pass of
:func:`~physsplat_jax.render.render_differentiable` per three labels (one
per colour channel), exact with the renderer's semantics (tiles, alpha cap,
early stop).

Votes are summed over views; pixels without a label (-1) vote for
"unlabelled". Gaussian k gets ``argmax_l sum_v W_v[k, l]`` if that beats its
unlabelled weight, else background (-1). Gaussians seen in no view (total
weight below ``min_weight``, e.g. the inside of an object) take the id of
the nearest decided Gaussian (``fill_unseen='nearest'``) or stay background.
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
import scipy.spatial
from absl import logging

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
  cot = jnp.asarray(cot, gaussians.means.dtype)
  camera = camera.unlabelled()
  config = config or RenderConfig()
  if config.capacity is None or config.max_chunks is None:
    config = fit_render_config(gaussians, camera, config)
  for _ in range(4):
    w, overflow = _weights_jit(gaussians, camera, cot, config)
    if not bool(overflow):
      break
    config = fit_render_config(gaussians, camera, config, margin=2.0)
  else:
    raise RuntimeError('contribution_weights: the renderer kept overflowing; '
                       'pass a RenderConfig with a larger capacity')
  w = np.asarray(w, np.float64).transpose(1, 0, 2).reshape(-1, G * 3)
  return w[:, :L + 1]


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
    min_weight: a Gaussian whose summed weight over all views is below this
      counts as unseen.
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
  for i, (cam, m) in enumerate(zip(cameras, masks)):
    w = contribution_weights(gaussians, cam, m, L, config)
    if not w.sum() > 0:
      logging.warning('lift_masks: camera %d sees none of the %d Gaussians '
                      '(its mask is ignored); check its pose', i,
                      gaussians.num)
    total += w
  if gaussians.num and not total.sum() > 0:
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
