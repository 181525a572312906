"""Scenes in and out: ``load_scene(name_or_path)`` and ``save_scene(path)``.

``load_scene`` accepts

* a built-in scene name (:func:`physsplat_jax.scenes.list_scenes`), built
  with :func:`physsplat_jax.scenes.make_scene` and its options;
* a 3DGS file: an INRIA PLY (binary LE/BE or ASCII), a PlayCanvas
  ``compressed.ply``, an antimatter15 ``.splat`` or a Niantic ``.spz``;
* a 3DGS output folder (``point_cloud/iteration_<N>/point_cloud.ply``, the
  highest ``N``, or the folder's only ``.ply``).

For a file, the scene is assembled from what lies next to it, in this order:

1. The sidecar ``<stem>.scene.json`` written by :func:`save_scene`: object
   names/materials/fixed flags/tags, up axis, metres per unit, scene name and
   the exact cameras. With it, ``load_scene(save_scene(p, s))`` gives ``s``
   back exactly (same arrays, same static fields).
2. Object ids: the first per-Gaussian property (kept by
   :func:`~physsplat_jax.io.ply.load_ply` in ``Gaussians.extras``) named one
   of :data:`ID_PROPERTIES` (case-insensitive), or ``object_property=``.
   Values must be integers (floats holding integers are accepted); negative
   values mean background (id -1). Distinct ids ``>= 0`` become objects
   ``0..n-1`` in increasing order, named ``object_<id>`` (tag ``ply_id=<id>``).
   The property is removed from ``extras`` (it lives in ``object_ids``).
   Without such a property every Gaussian is object 0, named after the file.
3. Cameras: the sidecar's; else ``cameras=`` (a camera file path); else an
   INRIA ``cameras.json``, a ``transforms.json`` or ``transforms_train.json``
   next to the file or in the 3DGS output folder above
   ``point_cloud/iteration_<N>/`` (read with
   :func:`~physsplat_jax.io.cameras.load_cameras`; one that cannot be read
   is an error that suggests ``cameras=False``); else ``num_cameras``
   orbit cameras fitted to the scene (:func:`physsplat_jax.cameras.
   fit_camera` around the 1st-99th percentile box of the centres, so
   floaters do not shrink the object).
4. Up axis (:func:`physsplat_jax.io.up_axis.guess_up`): ``up_axis=`` if
   given (not ``'auto'``); else the sidecar's; else, with cameras from a
   file, the cameras' mean up direction (captures are shot upright: ``-y``
   for typical COLMAP scenes); else the normal of the dominant plane of the
   centres (the ground), pointing to most of the mass; else ``'z'``. A
   direction within 5 degrees of a signed axis is snapped to it, any other
   is kept as ``'x,y,z'``. The choice is logged, and written to
   ``details`` (a dict) when one is passed.
"""

from __future__ import annotations

import glob
import json
import os
import re

import jax.numpy as jnp
import numpy as np
from absl import logging

from physsplat_jax.errors import PhysSplatError
from physsplat_jax import cameras as _cameras
from physsplat_jax.io.cameras import load_cameras
from physsplat_jax.io.ply import PlyError, load_ply, save_ply
from physsplat_jax.io.ply import check_writable_file, float_dtype
from physsplat_jax.io.ply_format import open_output, read_ply_header
from physsplat_jax.io.splat import load_splat
from physsplat_jax.io.spz import load_spz
from physsplat_jax.io import up_axis as up_lib
from physsplat_jax.types import Camera, DataError, Gaussians, ObjectInfo
from physsplat_jax.types import Scene
from physsplat_jax.types import make_camera, up_vector
from physsplat_jax.values import is_real, is_whole

PathLike = str | os.PathLike

# Per-Gaussian properties read as object ids, in order of preference (the
# one list: segmentation's attribute method uses it too).
ID_PROPERTIES = (
  'object_id', 'objectid', 'obj_id', 'object', 'instance_id', 'instance',
  'segment_id', 'segment', 'seg_id', 'segmentation', 'label', 'labels',
  'class_id', 'semantic_id', 'semantic', 'part_id', 'part',
)  # fmt: skip
SIDECAR_SUFFIX = '.scene.json'
SCENE_FORMAT = 'physsplat_jax.scene'
SCENE_VERSION = 1
DEFAULT_WIDTH, DEFAULT_HEIGHT, DEFAULT_FOV_DEG = 384, 288, 40.0
_FILE_OPTIONS = (
  'up_axis', 'meters_per_unit', 'object_property', 'cameras', 'num_cameras',
  'width', 'height', 'fov_deg', 'name', 'dtype', 'details',
)  # fmt: skip


class SceneFileError(PhysSplatError, ValueError):
  """A scene name, file or sidecar that cannot be loaded or written."""


def sidecar_path(path: PathLike) -> str:
  """``scene.ply`` -> ``scene.scene.json`` (the metadata next to a file)."""
  root, _ = os.path.splitext(os.fspath(path))
  return root + SIDECAR_SUFFIX


# ----------------------------------------------------------------------------
# Checks of option values and sidecar fields.


def _shown(value, as_json) -> str:
  try:
    text = json.dumps(value) if as_json else repr(value)
  except (TypeError, ValueError):
    text = repr(value)
  return text if len(text) <= 80 else text[:77] + '...'


class _Fields:
  """Checks values; errors name ``where``, the field, the value and a fix.

  ``sidecar=True`` shows ``field = <JSON value>`` (sidecar fields), else
  ``field=<repr>`` (keyword options).
  """

  def __init__(self, where: str, fix: str = '', sidecar: bool = True,
               prefix: str = ''):
    self.where, self.fix, self.sidecar, self.prefix = (
      where, fix, sidecar, prefix)

  def error(self, field, value, want) -> SceneFileError:
    sep = ' = ' if self.sidecar else '='
    fix = f'; {self.fix}' if self.fix else ''
    return SceneFileError(
      f'{self.where}: {self.prefix}{field}{sep}'
      f'{_shown(value, self.sidecar)}; {want}{fix}')

  def number(self, value, field, positive=False, default=None) -> float:
    if value is None and default is not None:
      return default
    if not (is_real(value) and (value > 0 or not positive)):
      raise self.error(field, value, 'must be a finite number'
                       + (' > 0' if positive else ''))
    return float(value)

  def whole(self, value, field, minimum=1, want='') -> int:
    if not (is_whole(value) and value >= minimum):
      raise self.error(field, value,
                       want or f'must be a whole number >= {minimum}')
    return int(value)

  def text(self, value, field, optional=False) -> str | None:
    if not (isinstance(value, str) or (optional and value is None)):
      raise self.error(field, value, 'must be a string'
                       + (' or null' if optional else ''))
    return value

  def up_axis(self, value, field='up_axis') -> str:
    if not isinstance(value, str):
      raise self.error(field, value, "must be a string such as 'z', '-y' "
                       "or 'x,y,z'")
    try:
      up_vector(value)
    except DataError as e:
      raise self.error(field, value, str(e)) from None
    return value


# Camera precisions a sidecar may name.
_CAMERA_DTYPES = ('float32', 'float64', 'float16', 'bfloat16')


def _sidecar_fields(data: dict, f: _Fields) -> dict:
  """The sidecar's fields checked: {name: value} of those present, with
  ``objects`` as ObjectInfo and ``cameras`` as make_camera arguments."""
  out = {}
  for key in ('name', 'id_property'):
    if key in data:
      out[key] = f.text(data[key], key, optional=key == 'id_property')
  if 'up_axis' in data:
    out['up_axis'] = f.up_axis(data['up_axis'])
  if 'meters_per_unit' in data:
    out['meters_per_unit'] = f.number(data['meters_per_unit'],
                                      'meters_per_unit', positive=True)
  for key, parse in (('objects', _object_fields),
                     ('cameras', _camera_fields)):
    if key in data:
      if not isinstance(data[key], list):
        raise f.error(key, data[key], 'must be a list')
      out[key] = tuple(parse(x, f, f'{key}[{i}]')
                       for i, x in enumerate(data[key]))
  return out


def _object_fields(o, f: _Fields, at: str) -> ObjectInfo:
  if not isinstance(o, dict) or 'name' not in o:
    raise f.error(at, o, 'must be an object with a "name"')
  fixed = o.get('fixed', False)
  if not isinstance(fixed, bool):
    raise f.error(f'{at}.fixed', fixed, 'must be true or false')
  tags = o.get('tags', [])
  if not isinstance(tags, (list, tuple)) or not all(
      isinstance(t, str) for t in tags):
    raise f.error(f'{at}.tags', tags, 'must be a list of strings')
  return ObjectInfo(
    name=f.text(o['name'], f'{at}.name'),
    material=f.text(o.get('material'), f'{at}.material', optional=True),
    fixed=fixed, tags=tuple(tags))


def _camera_fields(c, f: _Fields, at: str) -> dict:
  need = ('width', 'height', 'fx', 'fy', 'cx', 'cy', 'viewmat')
  if not isinstance(c, dict):
    raise f.error(at, c, f'must be an object with {", ".join(need)}')
  missing = [k for k in need if k not in c]
  if missing:
    raise SceneFileError(f'{f.where}: {f.prefix}{at} misses the field(s) '
                         f'{missing}' + (f'; {f.fix}' if f.fix else ''))
  kw = {k: f.whole(c[k], f'{at}.{k}') for k in ('width', 'height')}
  for k in ('fx', 'fy', 'cx', 'cy'):
    kw[k] = f.number(c[k], f'{at}.{k}', positive=k in ('fx', 'fy'))
  for k, default in (('near', 0.01), ('far', 1e10)):
    kw[k] = f.number(c.get(k, default), f'{at}.{k}', positive=True)
  try:
    vm = np.asarray(c['viewmat'], np.float64)
  except (TypeError, ValueError):
    vm = None
  if vm is None or vm.shape != (4, 4) or not np.all(np.isfinite(vm)):
    raise f.error(f'{at}.viewmat', c['viewmat'], 'must be a 4x4 list of '
                  'finite numbers (world-to-camera)')
  kw['viewmat'] = vm
  kw['name'] = f.text(c.get('name', ''), f'{at}.name')
  kw['dtype'] = c.get('dtype', 'float32')
  if kw['dtype'] not in _CAMERA_DTYPES:
    raise f.error(f'{at}.dtype', kw['dtype'], f'must be one of '
                  f'{", ".join(_CAMERA_DTYPES)}')
  return kw


def _check_output_path(path) -> None:
  """save_scene's two outputs, checked before either is written."""
  check_writable_file(path, 'scene PLY', SceneFileError)
  check_writable_file(sidecar_path(path), 'scene sidecar', SceneFileError)


# ----------------------------------------------------------------------------
# Loading.


def check_gaussians(g: Gaussians, path: str) -> None:
  """Refuses an empty or non-finite scene file; warns of absurd scales.

  Raises:
    SceneFileError: no Gaussians, or non-finite values (with the counts).
  """
  if g.num == 0:
    raise SceneFileError(f'{path}: the file holds no Gaussians (0 vertices); '
                         'give a trained 3DGS scene.')
  bad = {}
  for name in ('means', 'log_scales', 'quats', 'opacity_logits', 'sh'):
    a = np.asarray(getattr(g, name)).reshape(g.num, -1)
    n = int(np.sum(~np.all(np.isfinite(a), axis=1)))
    if n:
      bad[name] = n
  if bad:
    raise SceneFileError(
      f'{path}: non-finite values in {bad} (field: Gaussians affected); '
      'remove those vertices or re-export the scene.')
  means = np.asarray(g.means, np.float64)
  extent = float(np.max(np.ptp(means, axis=0))) if g.num > 1 else 0.0
  if g.num > 1 and extent == 0.0:
    logging.warning('%s: all %d Gaussians sit at one point (zero extent)',
                    path, g.num)
  scale = np.exp(np.max(np.asarray(g.log_scales, np.float64), axis=1))
  huge = int(np.sum(scale > max(extent, 1e-12)))
  if extent > 0 and huge:
    logging.warning(
      '%s: %d of %d Gaussians are larger than the whole scene (largest '
      'axis up to %.3g, scene extent %.3g): they will cover the frames; '
      'check the file\'s scale_* fields (log-scales expected).', path, huge,
      g.num, float(scale.max()), extent)
  # Activated opacity below a rasteriser's 1/255 cut-off: nothing is drawn.
  opacity = 1.0 / (1.0 + np.exp(-np.asarray(g.opacity_logits, np.float64)))
  if g.num and float(np.max(opacity)) < 1.0 / 255.0:
    logging.warning(
      '%s: every Gaussian is transparent (largest opacity %.3g < 1/255): '
      'the frames will show only the background; check the file\'s opacity '
      'field (logits expected, as 3DGS writes them).', path,
      float(np.max(opacity)))


def load_scene(path: str | PathLike, **options) -> Scene:
  """Loads a 3DGS scene file (``.ply`` / ``.splat`` / ``.spz``) or folder.

  Built-in scene names are :func:`physsplat_jax.load_scene`'s (it is
  :func:`physsplat_jax.scenes.load_scene`); this is the file loader only.

  Args:
    path: a ``.ply`` / ``.splat`` / ``.spz`` path, or a 3DGS output folder.
    **options: ``up_axis`` ('x', 'y', 'z', '-x', '-y', '-z', a direction
      'x,y,z', or 'auto' / None to guess it),
      ``meters_per_unit`` (> 0, default 1 or the sidecar's),
      ``object_property`` (a property name, or False to ignore ids),
      ``cameras`` (a camera file path, or False to skip camera files and fit
      an orbit), ``num_cameras`` (fitted orbit size, default 8), ``width`` /
      ``height`` (image size of fitted cameras, default 384x288; file
      cameras are resized when given), ``fov_deg`` (fitted cameras),
      ``name``, ``dtype`` (float32), ``details`` (a dict that receives
      how the up axis was chosen: ``UpGuess.to_dict()``, and where the
      cameras came from: ``cameras`` 'file', 'sidecar', 'fitted' or
      'none').

  Returns:
    A :class:`~physsplat_jax.types.Scene`.

  Raises:
    SceneFileError: missing path, unsupported file type, bad option values
      (named), bad sidecar fields (the file, field and value named), bad
      ids, or an unreadable camera file found next to the scene.
    PlyError, SplatError, CameraFileError: unreadable files (named).
    TypeError: unknown options.
  """
  if not isinstance(path, (str, os.PathLike)):
    raise SceneFileError(
      f'load_scene: expected a built-in scene name or a path, got '
      f'{type(path).__name__}')
  name_or_path = path
  path = os.fspath(name_or_path)
  if not os.path.exists(path):
    raise SceneFileError(
      f'load_scene: {path!r} does not exist; give an existing '
      '.ply/.splat/.spz file or 3DGS output folder'
    )
  bad = sorted(set(options) - set(_FILE_OPTIONS))
  if bad:
    raise TypeError(
      f'load_scene({path!r}): unknown option(s) {bad}; a scene file takes '
      f'{", ".join(_FILE_OPTIONS)}'
    )
  if os.path.isdir(path):
    path = _find_ply_in_dir(path)
  return load_scene_file(path, **options)


def _has_property(path: str, name: str) -> bool:
  """Whether the PLY header of ``path`` declares property ``name``."""
  try:
    header = read_ply_header(path)
  except (PlyError, OSError):
    return False
  return any(name in e.property_names for e in header.elements)


def _find_ply_in_dir(folder: str) -> str:
  its = glob.glob(os.path.join(folder, 'point_cloud', 'iteration_*',
                               'point_cloud.ply'))
  num = lambda p: int(re.sub(r'\D', '', os.path.basename(os.path.dirname(p)))
                      or -1)
  if its:
    return max(its, key=num)
  plys = sorted(glob.glob(os.path.join(folder, '*.ply')))
  if ([os.path.basename(p) for p in plys] == ['input.ply']
      and not _has_property(plys[0], 'f_dc_0')):
    # (read as a scene, it failed on its missing properties: f_dc_0, ...)
    raise SceneFileError(
      f'load_scene: folder {folder!r} holds only input.ply, the point cloud '
      "3DGS training starts from, not a trained scene: it has no "
      'point_cloud/iteration_*/point_cloud.ply yet. Finish the training, or '
      'pass a trained .ply')
  if len(plys) == 1:
    return plys[0]
  raise SceneFileError(
    f'load_scene: folder {folder!r} has no point_cloud/iteration_*/'
    f'point_cloud.ply and {len(plys)} .ply files at its top level; pass the '
    '.ply file itself'
  )


def load_scene_file(
  path: PathLike,
  *,
  up_axis: str | None = None,
  meters_per_unit: float | None = None,
  object_property: str | bool | None = None,
  cameras: PathLike | bool | None = None,
  num_cameras: int = 8,
  width: int | None = None,
  height: int | None = None,
  fov_deg: float = DEFAULT_FOV_DEG,
  name: str | None = None,
  dtype=jnp.float32,
  details: dict | None = None,
) -> Scene:
  """Loads a ``.ply`` / ``.splat`` / ``.spz`` file as a scene (load_scene)."""
  path = os.fspath(path)
  o = _Fields(f'load_scene({path!r})', sidecar=False)
  # Every option checked before the (slow) file is read.
  for field, v in (('width', width), ('height', height)):
    # (0 was taken for "unset" below and silently gave the default size.)
    if v is not None:
      o.whole(v, field, 1, want=(
        f'the image size must be >= 1 pixel (a whole number), or None '
        f'(cameras from a file keep theirs, fitted ones get '
        f'{DEFAULT_WIDTH}x{DEFAULT_HEIGHT})'))
  width = None if width is None else int(width)
  height = None if height is None else int(height)
  num_cameras = o.whole(num_cameras, 'num_cameras', 1)
  fov_deg = o.number(fov_deg, 'fov_deg', positive=True)
  if fov_deg >= 180:
    raise o.error('fov_deg', fov_deg, 'must be in (0, 180) degrees')
  if up_axis is not None and up_axis != 'auto':
    o.up_axis(up_axis)
  if meters_per_unit is not None:
    meters_per_unit = o.number(meters_per_unit, 'meters_per_unit',
                               positive=True)
  if not (cameras is None or isinstance(cameras, (bool, str, os.PathLike))):
    raise o.error('cameras', cameras, 'give a camera file path, False '
                  '(fit orbit cameras) or None (a camera file found next '
                  'to the scene, if any)')
  if name is not None:
    o.text(name, 'name')
  if details is not None and not isinstance(details, dict):
    raise o.error('details', details, 'give a dict (it receives how the up '
                  'axis was chosen) or None')
  float_dtype(dtype, o.where, SceneFileError)
  ext = os.path.splitext(path)[1].lower()
  if ext == '.ply':
    g = load_ply(path, dtype=dtype)
  elif ext == '.splat':
    g = load_splat(path, dtype=dtype)
  elif ext == '.spz':
    g = load_spz(path, dtype=dtype)
  else:
    raise SceneFileError(
      f'{path}: unsupported scene file type {ext or "(none)"!r}; expected '
      '.ply (INRIA or compressed), .splat or .spz'
    )
  check_gaussians(g, path)
  side = _read_sidecar(path)
  stem = os.path.splitext(os.path.basename(path))[0]

  # Object ids.
  prop = side.get('id_property') if side else None
  if object_property is False:
    prop = None
  elif isinstance(object_property, str):
    if object_property not in g.extras:
      raise SceneFileError(
        f'{path}: object_property={object_property!r} is not a property of '
        f'the file; per-Gaussian extras: {sorted(g.extras) or "none"}'
      )
    prop = object_property
  elif object_property is not None:
    raise SceneFileError(
      f'object_property must be a property name or False, got '
      f'{object_property!r}'
    )
  elif prop is None or prop not in g.extras:
    lower = {k.lower(): k for k in g.extras}
    prop = next((lower[p] for p in ID_PROPERTIES if p in lower), None)
  if prop is not None:
    raw = g.extras[prop]
    extras = {k: v for k, v in g.extras.items() if k != prop}
    g = g.replace(extras=extras)
    ids, objects = _ids_from_property(np.asarray(raw), prop, path, side)
  else:
    ids = np.zeros(g.num, np.int32)
    objects = None
  if side and 'objects' in side:
    objects = side['objects']
    if ids.size and ids.max() >= len(objects):
      raise SceneFileError(
        f'{path}: object id {int(ids.max())} but the sidecar '
        f'{sidecar_path(path)} lists {len(objects)} objects'
      )
  if objects is None:
    objects = (ObjectInfo(stem),)

  # Cameras and up axis.
  cams, from_file, exact = (), False, False
  if side and 'cameras' in side:
    cams = _sidecar_cameras(side['cameras'], path)
    exact = True  # even an empty list is what was saved
  elif cameras is not None and cameras is not False and cameras is not True:
    try:
      cams = tuple(load_cameras(cameras))
    except (IsADirectoryError, PermissionError) as e:
      raise o.error('cameras', cameras, f'cannot be read ({e.strerror}); '
                    'give a camera file path') from None
    from_file = True
  elif cameras is None or cameras is True:
    found = _find_camera_file(path)
    if found:
      cams = _found_cameras(found, path)
      from_file = True
  guess = up_lib.guess_up(
    np.asarray(g.means), np.asarray(g.opacities),
    cams if from_file else (), given=up_axis,
    sidecar=side.get('up_axis') if side else None)
  up_axis = guess.axis
  if guess.source not in ('given', 'sidecar'):
    logging.info('%s: up axis %s (%s: %s)', path, up_axis, guess.source,
                 guess.detail)
  if details is not None:
    details.update(guess.to_dict())
  if cams and (width is not None or height is not None):
    cams = tuple(
      c.resized(c.width if width is None else width,
                c.height if height is None else height) for c in cams
    )
  if not cams and not exact:
    try:
      cams = fitted_orbit(
        np.asarray(g.means), up_axis, num_cameras,
        DEFAULT_WIDTH if width is None else width,
        DEFAULT_HEIGHT if height is None else height, fov_deg,
      )
    except _cameras.CameraError as e:
      raise SceneFileError(f'{path}: {e}') from None
  if details is not None:  # (masks need the cameras they were taken with)
    details['cameras'] = ('file' if from_file else 'sidecar' if exact
                          else 'fitted' if cams else 'none')
  if meters_per_unit is None:
    meters_per_unit = side.get('meters_per_unit', 1.0) if side else 1.0
  if name is None:
    name = side.get('name', stem) if side else stem
  return Scene(
    gaussians=g,
    object_ids=jnp.asarray(ids, jnp.int32),
    objects=tuple(objects),
    cameras=tuple(cams),
    up_axis=up_axis,
    meters_per_unit=float(meters_per_unit),
    name=name,
  )


def _ids_from_property(raw, prop, path, side):
  if raw.dtype.kind == 'f':
    if not np.all(np.isfinite(raw)) or np.any(raw != np.round(raw)):
      raise SceneFileError(
        f'{path}: per-Gaussian property {prop!r} is read as object ids but '
        'holds non-integer values; pass object_property=False to ignore it '
        'or object_property=<name> to use another property'
      )
  raw = np.round(raw).astype(np.int64)
  if side and 'objects' in side:
    ids = np.where(raw < 0, -1, raw)
    return ids.astype(np.int32), None
  uniq = np.unique(raw[raw >= 0])
  ids = np.full(raw.shape, -1, np.int32)
  ids[raw >= 0] = np.searchsorted(uniq, raw[raw >= 0])
  objects = tuple(
    ObjectInfo(f'object_{u}', tags=(f'ply_id={u}',)) for u in uniq
  )
  return ids, objects


# Camera files looked for next to a scene file (not transforms*.json: an
# unrelated transforms_config.json must not be taken for cameras).
CAMERA_FILES = ('cameras.json', 'transforms.json', 'transforms_train.json')


def _find_camera_file(path: str) -> str | None:
  folders = [os.path.dirname(os.path.abspath(path))]
  # INRIA output: <model>/point_cloud/iteration_N/point_cloud.ply
  up2 = os.path.dirname(os.path.dirname(folders[0]))
  if os.path.basename(os.path.dirname(folders[0])) == 'point_cloud':
    folders.append(up2)
  for folder in folders:
    for fname in CAMERA_FILES:
      hit = os.path.join(folder, fname)
      if os.path.isfile(hit):
        return hit
  return None


def _found_cameras(found: str, path: str) -> tuple[Camera, ...]:
  """Cameras of a file found next to the scene; its errors say so."""
  try:
    return tuple(load_cameras(found))
  except (PhysSplatError, OSError, ValueError) as e:
    raise SceneFileError(
      f'{path}: the camera file {found} was found next to it automatically '
      f'but cannot be read ({e}); cameras are optional: fix that file or '
      'move it away (then orbit cameras are fitted), or in code pass '
      'cameras=False, or cameras=<path> to name the right file'
    ) from None


def fitted_orbit(
  means, up_axis: str = 'z', num_cameras: int = 8,
  width: int = DEFAULT_WIDTH, height: int = DEFAULT_HEIGHT,
  fov_deg: float = DEFAULT_FOV_DEG, elevation_deg: float = 25.0,
) -> tuple[Camera, ...]:
  """``num_cameras`` cameras around the scene, each framing all of it.

  The box is the 1st-99th percentile box of the centres (robust to
  floaters); see :func:`physsplat_jax.cameras.fit_camera`.
  """
  num_cameras = _Fields('fitted_orbit', sidecar=False).whole(
    num_cameras, 'num_cameras', 1)
  lo, hi = _cameras.framing_box(means)
  up = up_vector(up_axis)
  cams = []
  for i in range(int(num_cameras)):
    c = _cameras.fit_camera(
      lo, hi, up=up, width=int(width), height=int(height), fov_deg=fov_deg,
      azimuth=360.0 * i / int(num_cameras), elevation=elevation_deg,
      near=None, far=None,
    )
    cams.append(c.replace(name=f'orbit_{i:04d}'))
  return tuple(cams)


# ----------------------------------------------------------------------------
# The sidecar.


def _sidecar_fix(sp) -> str:
  return (f'fix that field (save_scene writes valid sidecars) or delete '
          f'{os.path.basename(sp)} to load the file without it')


def _read_sidecar(path: str) -> dict | None:
  """The checked fields of the sidecar next to ``path``, or None."""
  sp = sidecar_path(path)
  if not os.path.exists(sp):
    return None
  try:
    with open(sp) as f:
      data = json.load(f)
  except (OSError, ValueError) as e:
    raise SceneFileError(f'{sp}: cannot read the scene sidecar: {e}') from None
  if not isinstance(data, dict) or data.get('format') != SCENE_FORMAT:
    raise SceneFileError(
      f'{sp}: not a physsplat_jax scene sidecar (expected a JSON object '
      f'with "format": "{SCENE_FORMAT}"); rename or delete it'
    )
  fields = _Fields(sp, _sidecar_fix(sp))
  if 'version' in data:
    fields.whole(data['version'], 'version', 0, f'must be a whole number '
                 f'(this version writes {SCENE_VERSION})')
  if data.get('version', 0) > SCENE_VERSION:
    raise SceneFileError(
      f'{sp}: sidecar version {data.get("version")} is newer than this '
      f'physsplat_jax reads ({SCENE_VERSION}); upgrade physsplat_jax'
    )
  return _sidecar_fields(data, fields)


def _sidecar_cameras(items, path) -> tuple[Camera, ...]:
  sp = sidecar_path(path)
  out = []
  for i, kw in enumerate(items):
    kw = dict(kw, dtype=jnp.dtype(kw['dtype']))
    try:
      out.append(make_camera(**kw))
    except DataError as e:
      raise SceneFileError(
        f'{sp}: cameras[{i}]: {e}; {_sidecar_fix(sp)}') from None
  return tuple(out)


def _camera_to_json(c: Camera) -> dict:
  f = lambda x: float(np.asarray(x))
  return {
    'name': c.name,
    'width': int(c.width),
    'height': int(c.height),
    'fx': f(c.fx), 'fy': f(c.fy), 'cx': f(c.cx), 'cy': f(c.cy),
    'near': float(c.near), 'far': float(c.far),
    'viewmat': np.asarray(c.viewmat, np.float64).tolist(),
    'dtype': str(np.asarray(c.viewmat).dtype),
  }  # fmt: skip


# ----------------------------------------------------------------------------
# Saving.


def save_scene(path: PathLike, scene: Scene, *, binary: bool = True) -> str:
  """Writes a scene as a 3DGS PLY with an ``object_id`` property + sidecar.

  The PLY is a standard INRIA file (any 3DGS viewer opens it; the extra
  int ``object_id`` property is ignored by viewers). The sidecar
  ``<stem>.scene.json`` holds the objects, up axis, metres per unit, name
  and cameras, so that :func:`load_scene` restores the scene exactly.

  Args:
    path: output ``.ply`` path (parent folders are created).
    scene: the scene.
    binary: binary little-endian (True) or ASCII PLY.

  Returns:
    The sidecar path.

  Raises:
    SceneFileError: not a ``.ply`` path, a PLY or sidecar path that cannot
      be written (checked before either file is), object ids inconsistent
      with the objects, or scene fields the sidecar cannot hold (a
      non-finite ``meters_per_unit``, a bad up axis, camera values...).
    PlyError: Gaussians that cannot be written (non-finite values...).
  """
  if not isinstance(path, (str, os.PathLike)):
    raise SceneFileError(f'save_scene: expected a .ply path, got '
                         f'{type(path).__name__} {path!r}')
  path = os.fspath(path)
  if os.path.splitext(path)[1].lower() != '.ply':
    raise SceneFileError(
      f'save_scene: {path!r} must end in .ply (the object ids need a PLY '
      'property; export .splat with physsplat_jax.io.save_splat)'
    )
  g = scene.gaussians
  ids = np.asarray(scene.object_ids)
  if ids.shape != (g.num,) or ids.dtype.kind not in 'iu':
    raise SceneFileError(
      f'save_scene: object_ids must be ({g.num},) integers, got '
      f'{ids.dtype} {ids.shape}'
    )
  n = len(scene.objects)
  if ids.size and (ids.min() < -1 or ids.max() >= max(n, 1)):
    raise SceneFileError(
      f'save_scene: object ids span [{ids.min()}, {ids.max()}] but the '
      f'scene has {n} objects (ids must be -1 or 0..{n - 1})'
    )
  side = {
    'format': SCENE_FORMAT,
    'version': SCENE_VERSION,
    'name': scene.name,
    'up_axis': scene.up_axis,
    'meters_per_unit': float(scene.meters_per_unit),
    'id_property': 'object_id',
    'objects': [
      {'name': o.name, 'material': o.material,
       'fixed': bool(o.fixed) if isinstance(o.fixed, np.bool_) else o.fixed,
       'tags': o.tags if isinstance(o.tags, str) else list(o.tags)}
      for o in scene.objects
    ],
    'cameras': [_camera_to_json(c) for c in scene.cameras],
  }
  # What load_scene would refuse is refused now, before anything is written.
  _sidecar_fields(side, _Fields(f'save_scene({path!r})', 'fix the scene '
                                'before saving it', prefix='scene.'))
  text = json.dumps(side, indent=1, allow_nan=False) + '\n'
  _check_output_path(path)
  extras = dict(g.extras)
  extras['object_id'] = jnp.asarray(ids.astype(np.int32))
  save_ply(path, g.replace(extras=extras), binary=binary)
  sp = sidecar_path(path)
  with open_output(sp, 'scene sidecar', SceneFileError) as f:
    f.write(text.encode())
  return sp


__all__ = [
  'ID_PROPERTIES', 'PlyError', 'SceneFileError', 'fitted_orbit',
  'load_scene', 'load_scene_file', 'save_scene', 'sidecar_path',
]  # fmt: skip
