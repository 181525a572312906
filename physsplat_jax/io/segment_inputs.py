"""Segmentation inputs from files: label masks per camera, boxes as JSON.

**Masks** (:func:`load_masks`): a folder with one label image per view
(``.png``, ``.npy``; other image formats Pillow reads too), matched to the
scene's cameras by name: the file ``IMG_0012.png`` belongs to the camera
whose name (an INRIA ``img_name``, a ``transforms.json`` ``file_path``)
has the stem ``IMG_0012``. When no file stem is a camera's, and there are
as many files as cameras, they pair in sorted order. What a pixel says:

- a single-channel image (8 or 16-bit grey, palette PNG such as DAVIS or
  SAM-tracker output, ``.npy`` of integers): 0 is no object, value v >= 1
  is object v, the same v in every view;
- an RGB(A) image: each colour other than black is one object (the same
  colour in every view), black or a transparent pixel is no object.

A mask may be a uniformly downscaled view (``lift_masks`` resizes the
camera); masks of cameras the folder lacks are simply not used.

**Boxes** (:func:`load_boxes`): JSON, a list of objects (or
``{"objects": [...]}``), each ``{"name": "cup", "box": [xmin, xmax, ymin,
ymax, zmin, zmax], "fixed": false}`` in the scene file's coordinates (the
PLY's units and axes, as the Gaussians' means are stored).
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from os import PathLike

import numpy as np
from absl import logging

from physsplat_jax.errors import PhysSplatError
from physsplat_jax.types import Camera

MASK_SUFFIXES = ('.png', '.npy', '.tif', '.tiff', '.bmp', '.jpg', '.jpeg',
                 '.webp')


class SegmentInputError(PhysSplatError, ValueError):
  """Masks or boxes files that cannot be used."""


def _stem(name: str) -> str:
  return os.path.splitext(os.path.basename(str(name)))[0]


def _read_image(path: str) -> tuple[np.ndarray, str]:
  """(array, kind): kind 'labels' ((H, W) ints) or 'colours' ((H, W, 3),
  transparent pixels black)."""
  if path.lower().endswith('.npy'):
    try:
      a = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
      raise SegmentInputError(f'{path}: not a NumPy .npy array ({e})') from None
    if a.ndim != 2 or not np.issubdtype(a.dtype, np.integer):
      raise SegmentInputError(
        f'{path}: a .npy mask must be an (H, W) integer array (0 = no '
        f'object, v >= 1 = object v), got {a.dtype} {a.shape}')
    return a, 'labels'
  from PIL import Image  # (Pillow comes with imageio)
  try:
    with Image.open(path) as im:
      mode = im.mode
      if mode in ('P', 'L', 'I', 'I;16', 'I;16B', 'I;16L', '1'):
        return np.asarray(im).astype(np.int64), 'labels'
      if mode == 'LA':
        a = np.asarray(im)
        return np.where(a[..., 1] > 0, a[..., 0], 0).astype(np.int64), 'labels'
      rgba = np.asarray(im.convert('RGBA'))
  except OSError as e:
    raise SegmentInputError(
      f'{path}: not an image Pillow reads ({e})') from None
  rgb = np.where(rgba[..., 3:] > 0, rgba[..., :3], 0)
  if (rgb == rgb[..., :1]).all():
    return rgb[..., 0].astype(np.int64), 'labels'  # grey stored as RGB
  return rgb, 'colours'


def _mask_files(folder: str) -> list[str]:
  if not os.path.isdir(folder):
    raise SegmentInputError(
      f'masks folder {folder!r} does not exist; give a folder with one '
      'label image per camera (e.g. IMG_0012.png for camera IMG_0012)')
  files = sorted(f for f in os.listdir(folder)
                 if f.lower().endswith(MASK_SUFFIXES) and not f.startswith('.'))
  if not files:
    raise SegmentInputError(
      f'masks folder {folder!r} holds no label images '
      f'({", ".join(MASK_SUFFIXES)})')
  return files


def _pair(folder: str, files: list[str], cameras: Sequence[Camera]):
  """[(camera, file path)] by name, else in order."""
  by_stem = {_stem(f): f for f in files}
  pairs = [(c, by_stem[_stem(c.name)]) for c in cameras
           if c.name and _stem(c.name) in by_stem]
  if pairs:
    used = {f for _, f in pairs}
    unused = [f for f in files if f not in used]
    if unused:
      logging.warning('masks: %d file(s) in %s name no camera and are not '
                      'used: %s', len(unused), folder,
                      ', '.join(unused[:5]) + (' ...' if len(unused) > 5
                                               else ''))
    if len(pairs) < len(cameras):
      logging.info('masks: %d of %d cameras have a mask in %s', len(pairs),
                   len(cameras), folder)
    return [(c, os.path.join(folder, f)) for c, f in pairs]
  if len(files) == len(cameras):
    logging.info('masks: no file in %s is named after a camera; pairing the '
                 '%d files with the cameras in sorted order', folder,
                 len(files))
    return [(c, os.path.join(folder, f)) for c, f in zip(cameras, files)]
  names = ', '.join(_stem(c.name) or f'#{i}' for i, c in
                    enumerate(cameras[:4]))
  raise SegmentInputError(
    f'masks: none of the {len(files)} files in {folder!r} ({files[0]}, ...) '
    f'is named after one of the scene\'s {len(cameras)} cameras ({names}'
    f'{", ..." if len(cameras) > 4 else ""}): name each mask after its '
    'camera\'s image (IMG_0012.png for camera IMG_0012), or give exactly '
    'one mask per camera, sorted as the cameras are')


def _relabel(a: np.ndarray, lut: dict) -> np.ndarray:
  """``lut[v]`` per pixel, -1 where ``v`` is not in it."""
  u, inv = np.unique(a, return_inverse=True)
  ids = np.array([lut.get(v, -1) for v in u.tolist()], np.int32)
  return ids[inv].reshape(a.shape)


def load_masks(
  folder: str | PathLike,
  cameras: Sequence[Camera],
  names: Sequence[str] | None = None,
) -> tuple[list[Camera], list[np.ndarray], tuple[str, ...]]:
  """Label masks of a folder matched to cameras (module doc).

  Args:
    folder: the folder of label images.
    cameras: the scene's cameras.
    names: object names, for mask values 1, 2, ... (single-channel masks)
      or for the colours in first-seen order (RGB masks, sorted by file);
      default ``mask_<v>`` / ``colour_<rrggbb>``.

  Returns:
    ``(cameras, masks, names)`` for
    :func:`~physsplat_jax.segmentation.lift_masks`: the cameras that have a
    mask, (H, W) int32 masks with -1 for no object and 0..L-1 for objects,
    and L names.

  Raises:
    SegmentInputError: no folder, no images, no camera to pair with, a
      mask that mixes kinds, unreadable files, a wrong number of names.
  """
  folder = os.fspath(folder)
  if not cameras:
    raise SegmentInputError(
      f'masks {folder!r}: the scene has no cameras to lift masks with; load '
      'it with its cameras.json / transforms.json (an INRIA output folder)')
  pairs = _pair(folder, _mask_files(folder), cameras)
  images = [(c, p) + _read_image(p) for c, p in pairs]
  kinds = {k for _, _, _, k in images}
  if len(kinds) > 1:
    raise SegmentInputError(
      f'masks in {folder!r} mix single-channel label images and colour '
      'images; give one kind (the same object the same value or colour in '
      'every view)')
  if kinds == {'labels'}:
    for _, p, a, _ in images:
      if a.min() < 0:
        raise SegmentInputError(
          f'{p}: holds {int(a.min())}; mask values are 0 (no object) or '
          'v >= 1 (object v)')
    values = sorted(set().union(*(np.unique(a).tolist()
                                  for _, _, a, _ in images)) - {0})
    default = [f'mask_{v}' for v in values]
    lut = {v: i for i, v in enumerate(values)}
    masks = [_relabel(a, lut) for _, _, a, _ in images]
  else:
    colours: dict[int, int] = {}
    masks = []
    for _, _, a, _ in images:
      key = (a[..., 0].astype(np.int64) << 16) | (
        a[..., 1].astype(np.int64) << 8) | a[..., 2].astype(np.int64)
      for k in np.unique(key).tolist():
        if k and k not in colours:
          colours[k] = len(colours)
      masks.append(_relabel(key, colours))
    default = [f'colour_{k:06x}' for k in colours]
  if not default:
    raise SegmentInputError(
      f'masks in {folder!r} mark no object (every pixel is 0 / black): '
      'mark objects with values >= 1 or colours')
  if names is not None:
    names = tuple(str(n) for n in names)
    if len(names) != len(default):
      raise SegmentInputError(
        f'{len(names)} mask names for {len(default)} objects in the masks '
        f'of {folder!r} ({", ".join(default[:6])}'
        f'{", ..." if len(default) > 6 else ""}); give one name per object')
  else:
    names = tuple(default)
  return [c for c, _, _, _ in images], masks, names


def load_boxes(path: str | PathLike) -> dict:
  """Boxes from JSON (module doc).

  Returns:
    ``dict(boxes=(n, 6) float64, names=tuple, fixed=tuple of bool)`` for
    :func:`~physsplat_jax.segmentation.segment_by_boxes`.

  Raises:
    SegmentInputError: no file, not JSON, an entry without a 6-number
      ``box``, or a duplicate name.
  """
  path = os.fspath(path)
  try:
    with open(path, encoding='utf-8') as f:
      data = json.load(f)
  except OSError as e:
    raise SegmentInputError(f'boxes file {path!r}: {e.strerror}') from None
  except json.JSONDecodeError as e:
    raise SegmentInputError(f'{path}: not JSON ({e})') from None
  entries = data.get('objects') if isinstance(data, dict) else data
  example = ('[{"name": "cup", "box": [xmin, xmax, ymin, ymax, zmin, zmax], '
             '"fixed": false}, ...]')
  if not isinstance(entries, list) or not entries:
    raise SegmentInputError(
      f'{path}: expected a list of objects (or {{"objects": [...]}}), e.g. '
      f'{example}')
  boxes, names, fixed = [], [], []
  for i, e in enumerate(entries):
    if not isinstance(e, dict) or 'box' not in e:
      raise SegmentInputError(
        f'{path}: object {i} has no "box"; each entry is like {example}')
    try:
      b = np.asarray(e['box'], np.float64)
    except (TypeError, ValueError):
      b = np.zeros(0)
    if b.shape != (6,) or not np.isfinite(b).all():
      raise SegmentInputError(
        f'{path}: object {i} box {e["box"]!r} is not 6 finite numbers '
        '[xmin, xmax, ymin, ymax, zmin, zmax]')
    if (b[0::2] > b[1::2]).any():
      raise SegmentInputError(
        f'{path}: object {i} box {b.tolist()} has a min above its max; the '
        'order is [xmin, xmax, ymin, ymax, zmin, zmax]')
    name = str(e.get('name', f'box_{i}'))
    if name in names:
      raise SegmentInputError(f'{path}: two objects are named {name!r}')
    f = e.get('fixed', False)
    if not isinstance(f, bool):
      raise SegmentInputError(
        f'{path}: object {i} "fixed" is {f!r}; use true or false')
    boxes.append(b)
    names.append(name)
    fixed.append(f)
  return dict(boxes=np.stack(boxes), names=tuple(names), fixed=tuple(fixed))
