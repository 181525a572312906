"""Camera files -> lists of OpenCV :class:`~physsplat_jax.types.Camera`.

Three formats are read (REFERENCE section 6.5), and ``load_cameras`` picks
one by content:

* INRIA ``cameras.json`` (``gaussian-splatting/utils/camera_utils.py``,
  ``camera_to_JSON``): a list of ``{id, img_name, width, height,
  position: [3], rotation: [[3x3]], fx, fy}``. ``position`` is the camera
  centre and ``rotation`` the camera-to-world rotation (columns = camera axes)
  in the OpenCV convention, so ``viewmat = [R^T | -R^T position]``; the
  principal point is the image centre. :func:`save_inria_cameras` writes it.
* NeRF-synthetic ``transforms_{train,val,test}.json``: ``camera_angle_x``
  (horizontal FOV [rad]) and ``frames[{file_path, transform_matrix}]`` with an
  OpenGL/Blender camera-to-world matrix (+y up, +z backward); converted with
  ``c2w[:3, 1:3] *= -1`` (INRIA ``readCamerasFromTransforms``),
  ``fx = fy = W / (2 tan(camera_angle_x / 2))``, principal point at the
  centre. The image size is not in the file: it comes from ``w``/``h`` keys if
  present, else the ``width``/``height`` arguments, else the first image's
  header (``file_path`` + ``.png``).
* nerfstudio ``transforms.json`` (docs.nerf.studio, data conventions):
  ``fl_x fl_y cx cy w h`` (global or per frame; frame values win) and OpenGL
  camera-to-world ``transform_matrix`` per frame. nerfstudio's data
  processing rotates the COLMAP world by ``applied_transform`` (3x4, stored in
  the file) before writing the poses: ``c2w_file = A c2w_colmap``. With
  ``undo_applied_transform=True`` the cameras are mapped back,
  ``c2w = A^-1 c2w_file``, so that they match a PLY trained on the original
  COLMAP data (e.g. by the INRIA code). Distortion (``k1..k4, p1, p2``) is
  ignored with a warning (pinhole only); fisheye/equirectangular models are
  rejected.

Pixel centres: all three use the OpenCV/COLMAP continuous pixel coordinates
in which pixel ``(i, j)`` covers ``[j, j+1) x [i, i+1)``, as we do.
"""

from __future__ import annotations

import json
import math
import os
import warnings

import jax.numpy as jnp
import numpy as np

from physsplat_jax.errors import PhysSplatError
from physsplat_jax.io import paths
from physsplat_jax.types import Camera, DataError
from physsplat_jax.types import make_camera


class CameraFileError(PhysSplatError, ValueError):
  """A camera file that cannot be read."""


# Largest image side accepted from a file [pixels]: a bigger "width" is a
# corrupt field (1e300 gave an infinite principal point), not a camera.
_MAX_SIZE = 1 << 16


def _file_camera(path, what, vm, fx, fy, w, h, cx=None, cy=None, *,
                 dtype=jnp.float32, **kwargs) -> Camera:
  """``types.make_camera``, its errors naming the file and the camera.

  The intrinsics are float64 here; one that overflows ``dtype`` (1e300 in
  float32) would turn into inf in the camera, so it is refused first.
  """
  big = float(jnp.finfo(dtype).max)
  values = {'fx': fx, 'fy': fy, 'cx': w / 2 if cx is None else cx,
            'cy': h / 2 if cy is None else cy}
  for key, v in values.items():
    if not abs(v) <= big:
      raise CameraFileError(
        f'{path}: {what}: {key!r}={v:g} does not fit the camera dtype '
        f'{np.dtype(dtype).name} (at most {big:g}); check the file\'s '
        'intrinsics and image size')
  try:
    return make_camera(vm, fx, fy, w, h, cx, cy, dtype=dtype, **kwargs)
  except DataError as e:
    raise CameraFileError(f'{path}: {what}: {e}') from None


def _camera_files_in(folder) -> list[str]:
  try:
    names = sorted(os.listdir(folder))
  except OSError:
    return []
  return [n for n in names if n == 'cameras.json' or (
    n.startswith('transforms') and n.endswith('.json'))]


def _read_json(path):
  try:
    with open(path, encoding='utf-8') as f:
      return json.load(f)
  except FileNotFoundError:
    raise FileNotFoundError(f'camera file not found: {path}') from None
  except IsADirectoryError:
    found = _camera_files_in(path)
    hint = (f'it holds {found}' if found else 'it holds no cameras.json or '
            'transforms*.json')
    raise CameraFileError(
      f'{path}: is a directory, not a camera file ({hint}); pass the file '
      'itself, e.g. <dir>/cameras.json or <dir>/transforms.json') from None
  except (json.JSONDecodeError, UnicodeDecodeError) as e:
    raise CameraFileError(f'{path}: not valid JSON ({e})') from None


def _matrix(value, shape_ok, path, what) -> np.ndarray:
  try:
    a = np.asarray(value, np.float64)
  except (TypeError, ValueError):
    raise CameraFileError(
      f'{path}: {what} is not a numeric matrix: {value!r}'
    ) from None
  if a.shape not in shape_ok:
    raise CameraFileError(
      f'{path}: {what} has shape {a.shape}; expected one of {shape_ok}'
    )
  if not np.all(np.isfinite(a)):
    raise CameraFileError(f'{path}: {what} has non-finite values')
  return a


def _number(d, key, path, what, positive=True) -> float:
  if key not in d:
    raise CameraFileError(f'{path}: {what} has no {key!r} field')
  try:
    if isinstance(d[key], bool):  # (true was a width of 1 pixel)
      raise TypeError
    v = float(d[key])
  except (TypeError, ValueError):
    raise CameraFileError(
      f'{path}: {what} field {key!r} is not a number: {d[key]!r}'
    ) from None
  if not math.isfinite(v) or (positive and v <= 0):
    raise CameraFileError(
      f'{path}: {what} field {key!r} must be a finite'
      f'{" positive" if positive else ""} number, got {v}'
    )
  return v


def _size(d, key, path, what) -> int:
  v = _number(d, key, path, what)
  if v != int(v):
    raise CameraFileError(f'{path}: {what} field {key!r} = {v} is not whole')
  if v > _MAX_SIZE:
    raise CameraFileError(
      f'{path}: {what} field {key!r} = {v:g} pixels is not an image size '
      f'(at most {_MAX_SIZE}); fix the field')
  return int(v)


def _angle(d, key, path, what) -> float:
  """A field of view [radians] in (0, pi): 40 is degrees given by mistake
  (fx = 14 for 800 px), pi a degenerate tan (fx ~ 0)."""
  v = _number(d, key, path, what, positive=False)
  # Within 1e-3 of pi the focal length is below W / 4000 pixels.
  if not 0.0 < v < math.pi - 1e-3:
    hint = (f'; if {v:g} is degrees, that is {math.radians(v):.6g} rad'
            if math.pi <= v < 180.0 else '')
    raise CameraFileError(
      f'{path}: {what} field {key!r}={v:g} must be in (0, pi) radians '
      f'(degrees given?){hint}')
  return v


# ----------------------------------------------------------------------------
# INRIA cameras.json


def inria_cameras_from_json(
  data, path='<json>', dtype=jnp.float32, near=0.01, far=1e10
) -> list[Camera]:
  """Parses INRIA ``cameras.json`` content (a list of dicts).

  Args:
    data: the decoded JSON list.
    path: used in error messages.
    dtype: float dtype of the camera arrays.
    near, far: clipping depths for every camera.

  Returns:
    One :class:`~physsplat_jax.types.Camera` per entry, named ``img_name``.

  Raises:
    CameraFileError: not a list, an empty list, or an entry missing
      ``width``, ``height``, ``position``, ``rotation``, ``fx`` or ``fy``
      or holding a bad value (the field is named).
  """
  if not isinstance(data, list):
    raise CameraFileError(
      f'{path}: an INRIA cameras.json is a JSON list of cameras, got '
      f'{type(data).__name__}'
    )
  if not data:
    raise CameraFileError(
      f'{path}: the JSON list is empty: the file holds no cameras (an INRIA '
      'cameras.json lists one entry per training image)')
  cams = []
  for i, d in enumerate(data):
    what = f'camera {i}'
    if not isinstance(d, dict):
      raise CameraFileError(f'{path}: {what} is not a JSON object')
    missing = [
      k for k in ('width', 'height', 'position', 'rotation', 'fx', 'fy')
      if k not in d
    ]
    if missing:
      raise CameraFileError(
        f'{path}: {what} ({d.get("img_name", "?")}) is missing {missing}; '
        'INRIA cameras need id, img_name, width, height, position, '
        'rotation, fx, fy'
      )
    w, h = _size(d, 'width', path, what), _size(d, 'height', path, what)
    pos = _matrix(d['position'], [(3,)], path, f'{what} position')
    rot = _matrix(d['rotation'], [(3, 3)], path, f'{what} rotation')
    vm = _exact_viewmat(rot.T, -rot.T @ pos)
    cams.append(
      _file_camera(
        path, what, vm,
        _number(d, 'fx', path, what),
        _number(d, 'fy', path, what),
        w,
        h,
        near=near,
        far=far,
        name=str(d.get('img_name', d.get('id', i))),
        dtype=dtype,
      )
    )
  return cams


def _exact_viewmat(R, t) -> np.ndarray:
  vm = np.eye(4)
  vm[:3, :3] = R
  vm[:3, 3] = t
  return vm


def load_inria_cameras(path, dtype=jnp.float32, near=0.01, far=1e10):
  """Loads an INRIA ``cameras.json``; see :func:`inria_cameras_from_json`."""
  return inria_cameras_from_json(_read_json(path), path, dtype, near, far)


def inria_cameras_to_json(cameras) -> list[dict]:
  """Cameras -> INRIA ``cameras.json`` entries (principal point dropped).

  Args:
    cameras: a sequence of :class:`~physsplat_jax.types.Camera`.

  Returns:
    A list of ``{id, img_name, width, height, position, rotation, fy, fx}``.
  """
  out = []
  for i, c in enumerate(cameras):
    vm = np.asarray(c.viewmat, np.float64)
    R, t = vm[:3, :3], vm[:3, 3]
    out.append({
      'id': i,
      'img_name': c.name or f'{i:05d}',
      'width': int(c.width),
      'height': int(c.height),
      'position': (-R.T @ t).tolist(),
      'rotation': R.T.tolist(),
      'fy': float(c.fy),
      'fx': float(c.fx),
    })
  return out


def save_inria_cameras(path, cameras) -> None:
  """Writes cameras as an INRIA ``cameras.json`` (SuperSplat/antimatter15).

  The principal point is not stored (the format assumes the image centre).
  """
  text = json.dumps(inria_cameras_to_json(cameras))
  p = paths.check_output_file(path, CameraFileError, what='cameras',
                              create=True)
  paths.write_data(p, text.encode('utf-8'), CameraFileError, what='cameras')


# ----------------------------------------------------------------------------
# transforms.json (NeRF-synthetic and nerfstudio)

_UNSUPPORTED_MODELS = ('OPENCV_FISHEYE', 'EQUIRECTANGULAR', 'FISHEYE624')
_DISTORTION = ('k1', 'k2', 'k3', 'k4', 'p1', 'p2')


def _image_size(path, file_path):
  """(W, H) of a frame's image, trying ``file_path`` then ``+ '.png'``."""
  base = os.path.dirname(os.fspath(path))
  for cand in (file_path, file_path + '.png'):
    full = os.path.join(base, cand)
    if os.path.isfile(full):
      try:
        import imageio.v3 as iio

        shape = iio.improps(full).shape
        return int(shape[1]), int(shape[0])
      except Exception as e:  # noqa: BLE001 - any decoder failure
        raise CameraFileError(
          f'{path}: cannot read the size of image {full} ({e}); pass '
          'width= and height='
        ) from None
  return None


def transforms_cameras_from_json(
  data,
  path='<json>',
  *,
  width: int | None = None,
  height: int | None = None,
  undo_applied_transform: bool = False,
  dtype=jnp.float32,
  near=0.01,
  far=1e10,
) -> list[Camera]:
  """Parses a NeRF-synthetic or nerfstudio ``transforms*.json`` dict.

  Intrinsics are looked up per frame first, then globally: ``fl_x``/``fl_y``
  (pixels) or ``camera_angle_x``/``camera_angle_y`` (radians); ``cx``/``cy``
  default to the image centre; ``w``/``h`` (or ``width``/``height`` args, or
  the image file) give the size.

  Args:
    data: the decoded JSON object.
    path: the file path (images are looked up relative to it).
    width, height: image size when the file does not give it.
    undo_applied_transform: map poses back through nerfstudio's
      ``applied_transform`` (see the module docstring).
    dtype: float dtype of the camera arrays.
    near, far: clipping depths.

  Returns:
    One :class:`~physsplat_jax.types.Camera` per frame, named ``file_path``.

  Raises:
    CameraFileError: no frames, missing ``transform_matrix`` or one whose
      last row is not ``[0, 0, 0, 1]`` (transposed), no focal length, a
      ``camera_angle_x/y`` outside (0, pi) radians, no image size, a
      non-numeric field, a singular ``applied_transform`` to undo, or an
      unsupported camera model.
  """
  if not isinstance(data, dict) or 'frames' not in data:
    raise CameraFileError(
      f'{path}: a transforms.json is a JSON object with a "frames" list'
    )
  _check_frames(data['frames'], path)
  model = str(data.get('camera_model', 'OPENCV')).upper()
  if model in _UNSUPPORTED_MODELS:
    raise CameraFileError(
      f'{path}: camera_model {model} is not supported (pinhole only); '
      'undistort the images first (e.g. ns-process-data / COLMAP undistorter)'
    )
  A = None
  if undo_applied_transform:
    if 'applied_transform' not in data:
      raise CameraFileError(
        f'{path}: undo_applied_transform=True but the file has no '
        '"applied_transform"'
      )
    A = np.eye(4)
    A[:3] = _matrix(
      data['applied_transform'], [(3, 4)], path, 'applied_transform'
    )
    sv = np.linalg.svd(A[:3, :3], compute_uv=False)
    if not sv[-1] > 1e-9 * max(sv[0], 1.0):
      raise CameraFileError(
        f'{path}: applied_transform {A[:3].tolist()} is singular (its 3x3 '
        'block cannot be inverted) so undo_applied_transform=True cannot '
        'map the poses back; fix the field or load with '
        'undo_applied_transform=False')
    A = np.linalg.inv(A)
  distorted = False
  cams = []
  size_from_image = None
  for i, fr in enumerate(data['frames']):
    what = f'frame {i}'
    if not isinstance(fr, dict):
      raise CameraFileError(f'{path}: {what} is not a JSON object')
    if 'transform_matrix' not in fr:
      raise CameraFileError(
        f'{path}: {what} has no "transform_matrix" (4x4 OpenGL '
        'camera-to-world)'
      )
    c2w = _matrix(
      fr['transform_matrix'], [(4, 4), (3, 4)], path,
      f'{what} transform_matrix'
    )  # fmt: skip
    if len(c2w) == 4 and not np.allclose(c2w[3], (0, 0, 0, 1), rtol=0,
                                         atol=1e-6):
      row = ', '.join(f'{x:g}' for x in c2w[3])
      raise CameraFileError(
        f'{path}: {what} transform_matrix last row [{row}] must be '
        '[0, 0, 0, 1] (transposed?); the translation belongs in the last '
        'column of the row-major camera-to-world matrix')
    c2w = np.concatenate([c2w[:3], [[0.0, 0.0, 0.0, 1.0]]])
    if A is not None:
      c2w = A @ c2w
    merged = {**data, **fr}
    distorted |= any(
      merged.get(k) is not None
      and _number(merged, k, path, what, positive=False) != 0.0
      for k in _DISTORTION)
    name = str(fr.get('file_path', i))
    if 'w' in merged and 'h' in merged:
      w, h = _size(merged, 'w', path, what), _size(merged, 'h', path, what)
    elif width is not None and height is not None:
      w, h = int(width), int(height)
    else:
      if size_from_image is None:
        size_from_image = _image_size(path, name)
      if size_from_image is None:
        raise CameraFileError(
          f'{path}: {what} has no image size: the file has no "w"/"h", '
          f'the image {name!r} was not found next to it, and no width=/'
          'height= were passed (NeRF-synthetic images are 800x800)'
        )
      w, h = size_from_image
    if 'fl_x' in merged:
      fx = _number(merged, 'fl_x', path, what)
      fy = _number(merged, 'fl_y', path, what) if 'fl_y' in merged else fx
    elif 'camera_angle_x' in merged:
      ax = _angle(merged, 'camera_angle_x', path, what)
      fx = 0.5 * w / math.tan(0.5 * ax)
      if 'camera_angle_y' in merged:
        ay = _angle(merged, 'camera_angle_y', path, what)
        fy = 0.5 * h / math.tan(0.5 * ay)
      else:
        fy = fx
    else:
      raise CameraFileError(
        f'{path}: {what} has no focal length: give "fl_x" (and "fl_y") in '
        'pixels or "camera_angle_x" in radians, globally or per frame'
      )
    cx = _number(merged, 'cx', path, what, False) if 'cx' in merged else w / 2
    cy = _number(merged, 'cy', path, what, False) if 'cy' in merged else h / 2
    R = c2w[:3, :3] * np.array([1.0, -1.0, -1.0])  # OpenGL -> OpenCV axes
    vm = _exact_viewmat(R.T, -R.T @ c2w[:3, 3])
    cams.append(
      _file_camera(path, what, vm, fx, fy, w, h, cx, cy, near=near,
                   far=far, name=name, dtype=dtype)
    )  # fmt: skip
  if not cams:
    raise CameraFileError(f'{path}: "frames" is empty')
  if distorted:
    warnings.warn(
      f'{path}: lens distortion coefficients are ignored (pinhole model); '
      'use undistorted images for exact reprojection',
      stacklevel=2,
    )
  return cams


def load_transforms_cameras(path, **kwargs) -> list[Camera]:
  """Loads a NeRF-synthetic or nerfstudio ``transforms*.json``.

  Keyword arguments are those of :func:`transforms_cameras_from_json`.
  """
  return transforms_cameras_from_json(_read_json(path), path, **kwargs)


# Aliases that name the two dialects.
load_nerf_synthetic_cameras = load_transforms_cameras
load_nerfstudio_cameras = load_transforms_cameras


def _check_frames(frames, path=None) -> None:
  """A transforms file's ``frames`` must be a list (of frame objects)."""
  if not isinstance(frames, list):
    where = f'{path}: ' if path is not None else ''
    raise CameraFileError(
      f'{where}"frames" must be a list of frame objects '
      '({"file_path": ..., "transform_matrix": [[4x4]]}), got '
      f'{type(frames).__name__} {str(frames)[:40]}')


def camera_format(data) -> str:
  """``'inria'``, ``'nerf_synthetic'`` or ``'nerfstudio'`` for decoded JSON.

  Raises:
    CameraFileError: for anything else.
  """
  if isinstance(data, list):
    if not data:
      raise CameraFileError(
        'the JSON list is empty: the file holds no cameras (an INRIA '
        'cameras.json lists one entry per training image)')
    if isinstance(data[0], dict) and 'rotation' in data[0]:
      return 'inria'
    raise CameraFileError(
      'a JSON list of cameras must hold INRIA entries with "position" and '
      '"rotation"'
    )
  if isinstance(data, dict) and 'frames' in data:
    _check_frames(data['frames'])
    has_fl = 'fl_x' in data or any(
      isinstance(f, dict) and 'fl_x' in f for f in data['frames'][:1]
    )
    return 'nerfstudio' if has_fl else 'nerf_synthetic'
  raise CameraFileError(
    'unknown camera file: expected an INRIA cameras.json (a list of '
    'cameras) or a transforms.json (an object with "frames")'
  )


def load_cameras(path, **kwargs) -> list[Camera]:
  """Loads any supported camera file, dispatching on its content.

  Args:
    path: an INRIA ``cameras.json``, a NeRF-synthetic
      ``transforms_*.json`` or a nerfstudio ``transforms.json``.
    **kwargs: ``dtype``, ``near``, ``far`` for all formats; ``width``,
      ``height``, ``undo_applied_transform`` for transforms files.

  Returns:
    A list of OpenCV :class:`~physsplat_jax.types.Camera`.

  Raises:
    CameraFileError: unknown layout or missing fields (named in the message).
  """
  data = _read_json(path)
  try:
    fmt = camera_format(data)
  except CameraFileError as e:
    raise CameraFileError(f'{path}: {e}') from None
  if fmt == 'inria':
    bad = set(kwargs) - {'dtype', 'near', 'far'}
    if bad:
      raise TypeError(
        f'load_cameras: {sorted(bad)} do not apply to INRIA cameras.json'
      )
    return inria_cameras_from_json(data, path, **kwargs)
  return transforms_cameras_from_json(data, path, **kwargs)
