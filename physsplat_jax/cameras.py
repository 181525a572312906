"""Pure camera utilities: look-at view matrices, orbits, framing, conventions.

Conventions (see :mod:`physsplat_jax.types`): cameras are OpenCV/COLMAP, a
world-to-camera ``viewmat`` ``[R | t]`` maps a world point ``p`` to camera
coordinates ``R p + t`` with +x right, +y down, +z forward; pixel ``(i, j)``
has its centre at ``(j + 0.5, i + 0.5)`` and a centred principal point is
``(W / 2, H / 2)``.

``look_at(eye, target, up)`` builds the rows of ``R`` as::

  z = normalize(target - eye)        forward
  x = normalize(z x up)              right
  y = z x x                          down (so the world ``up`` maps to -y)
  t = -R eye

OpenGL/Blender cameras (NeRF-synthetic, nerfstudio) look down -z with +y up;
their camera-to-world matrix becomes OpenCV by negating its y and z columns
(``c2w[:3, 1:3] *= -1``, INRIA ``readCamerasFromTransforms``).

The pinhole focal length for a field of view ``fov`` across ``n`` pixels is
``f = n / (2 tan(fov / 2))``.

Everything here is jnp (differentiable, jit-able) except the camera lists,
which are built on the host.
"""

from __future__ import annotations

import math
import operator

import jax
import jax.numpy as jnp
import numpy as np

from physsplat_jax.errors import PhysSplatError
from physsplat_jax.types import Array, Camera, device_array, is_host_data
from physsplat_jax.types import make_camera


class CameraError(PhysSplatError, ValueError):
  """A camera that cannot be built or used (sizes, focal lengths, poses);
  the message names the value."""


# Below this norm the forward and up directions are treated as parallel.
_PARALLEL_EPS = 1e-6


def _is_concrete(*xs) -> bool:
  return not any(isinstance(x, jax.core.Tracer) for x in xs)


def _normalize(v: Array) -> Array:
  n = jnp.linalg.norm(v)
  return v / jnp.where(n > 0, n, 1.0)


def focal_from_fov(fov_deg, size) -> float | Array:
  """Focal length [pixels] for a field of view [degrees] across ``size`` px."""
  return _focal_from_fov(fov_deg, size)


# One compiled program each, where eager calls on concrete values compiled
# one per operation (~14 ms each on the CPU; a scene's camera set took ~40).
@jax.jit
def _focal_from_fov(fov_deg, size):
  return size / (2.0 * jnp.tan(jnp.deg2rad(fov_deg) / 2.0))


def fov_from_focal(focal, size) -> float | Array:
  """Field of view [degrees] of a focal length [pixels] across ``size`` px."""
  return jnp.rad2deg(2.0 * jnp.arctan(size / (2.0 * focal)))


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> Array:
  """OpenCV world-to-camera matrix of a camera at ``eye`` looking at ``target``.

  The target projects to the principal point, and ``up`` points to -y (up in
  the image). If ``up`` is parallel to the viewing direction, a perpendicular
  up is chosen (the world axis least aligned with the view).

  Args:
    eye: (3,) camera centre [scene units].
    target: (3,) point to look at.
    up: (3,) world up direction (need not be unit).

  Returns:
    (4, 4) world-to-camera ``viewmat`` (+x right, +y down, +z forward).

  Raises:
    ValueError: non-numeric or non-finite inputs, ``eye == target`` or a
      zero ``up`` (when the inputs are concrete; under ``jit`` the result is
      then undefined).
  """
  if is_host_data(eye):
    eye = _numeric('eye', eye)
  # float64 stays float64 only with x64 on (canonicalised, as jnp.asarray).
  dtype = jnp.result_type(jax.dtypes.canonicalize_dtype(eye.dtype),
                          jnp.float32)
  eye = device_array(eye, dtype)
  target = device_array(_numeric('target', target), dtype)
  up = device_array(_numeric('up', up), dtype)
  for name, v in (('eye', eye), ('target', target), ('up', up)):
    if v.shape != (3,):
      raise CameraError(f'look_at: {name} has shape {v.shape}; expected (3,)')
  if _is_concrete(eye, target, up):
    # Checked in NumPy (exact zeros): no eager JAX operation to compile.
    for name, v in (('eye', eye), ('target', target), ('up', up)):
      if not np.all(np.isfinite(np.asarray(v))):
        raise CameraError(
          f'look_at: {name} {np.asarray(v).tolist()} has non-finite values; '
          'pass finite coordinates')
    if not np.any(np.asarray(target) - np.asarray(eye)):
      raise CameraError(
        f'look_at: eye and target are the same point {np.asarray(eye)}; '
        'place the camera away from what it looks at'
      )
    if not np.any(np.asarray(up)):
      raise CameraError('look_at: up is the zero vector; pass e.g. (0, 0, 1)')
  return _look_at(eye, target, up)


def _numeric(name, v):
  """``v`` unchanged if a JAX array or tracer, else as a numeric NumPy
  array (strings and ragged lists refused by name)."""
  if not is_host_data(v):
    return v
  try:
    a = np.asarray(v)
  except ValueError:
    a = np.asarray(None)
  if not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
    raise CameraError(
      f'look_at: {name} is not numeric: {v!r}; pass 3 numbers (x, y, z)')
  return a


@jax.jit
def _look_at(eye, target, up):
  """:func:`look_at`'s matrix, one compiled program (see above)."""
  dtype = eye.dtype
  z = _normalize(target - eye)
  up = _normalize(up)
  x = jnp.cross(z, up)
  # Fallback up for a vertical view: the world axis least aligned with z.
  alt = jnp.eye(3, dtype=dtype)[jnp.argmin(jnp.abs(z))]
  x = jnp.where(jnp.linalg.norm(x) > _PARALLEL_EPS, x, jnp.cross(z, alt))
  x = _normalize(x)
  y = jnp.cross(z, x)
  R = jnp.stack([x, y, z])
  out = jnp.eye(4, dtype=dtype)
  out = out.at[:3, :3].set(R)
  return out.at[:3, 3].set(-R @ eye)


def opengl_c2w_to_viewmat(c2w) -> Array:
  """OpenGL/Blender camera-to-world (4x4 or 3x4) -> OpenCV world-to-camera.

  Args:
    c2w: (4, 4) or (3, 4) camera-to-world with camera axes +x right, +y up,
      +z backward (NeRF-synthetic, nerfstudio).

  Returns:
    (4, 4) OpenCV world-to-camera ``viewmat``.
  """
  c2w = jnp.asarray(c2w)
  R = c2w[:3, :3] * jnp.array([1.0, -1.0, -1.0], c2w.dtype)
  return opencv_c2w_to_viewmat(R, c2w[:3, 3])


def opencv_c2w_to_viewmat(rotation, position) -> Array:
  """OpenCV camera-to-world rotation (3x3) and centre (3,) -> viewmat (4x4)."""
  R = jnp.asarray(rotation).T
  t = -R @ jnp.asarray(position, R.dtype)
  out = jnp.eye(4, dtype=R.dtype)
  out = out.at[:3, :3].set(R)
  return out.at[:3, 3].set(t)


def viewmat_to_opengl_c2w(viewmat) -> Array:
  """OpenCV world-to-camera (4x4) -> OpenGL camera-to-world (4x4)."""
  viewmat = jnp.asarray(viewmat)
  R = viewmat[:3, :3]
  out = jnp.eye(4, dtype=viewmat.dtype)
  out = out.at[:3, :3].set(R.T * jnp.array([1.0, -1.0, -1.0], R.dtype))
  return out.at[:3, 3].set(-R.T @ viewmat[:3, 3])


def _orbit_basis(up) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Unit up and two horizontal axes (e1, e2 = up x e1) for azimuths."""
  up = np.asarray(up, np.float64)
  if up.shape != (3,) or not np.all(np.isfinite(up)) or not up.any():
    raise CameraError(f'up must be a finite nonzero (3,) vector, got {up}')
  u = up / np.linalg.norm(up)
  # Azimuth 0 looks from the world axis most perpendicular to up (+x for a
  # z-up or y-up world), so azimuths agree across those worlds.
  ref = np.eye(3)[1] if abs(u[0]) > 0.9 else np.eye(3)[0]
  e1 = ref - u * (ref @ u)
  e1 /= np.linalg.norm(e1)
  e2 = np.cross(u, e1)
  return u, e1, e2


def orbit_position(center, radius, azimuth_deg, elevation_deg, up=(0, 0, 1)):
  """Camera centre on a sphere around ``center``.

  Azimuth turns counter-clockwise about ``up`` (seen from above) starting at
  the horizontal direction closest to world +x; elevation is measured from the
  horizontal plane towards ``up``.

  Returns:
    (3,) NumPy float64 position.
  """
  u, e1, e2 = _orbit_basis(up)
  az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
  d = math.cos(el) * (math.cos(az) * e1 + math.sin(az) * e2)
  return np.asarray(center, np.float64) + radius * (d + math.sin(el) * u)


def orbit_viewmat(viewmat, center, axis, angle_deg) -> Array:
  """World-to-camera matrix of a camera turned about an axis.

  The camera (its centre and orientation) turns by ``angle_deg`` about the
  line through ``center`` along ``axis``, counter-clockwise seen from
  ``+axis``: a point ``x`` of the turned camera's view is the point
  ``R^T (x - c) + c`` of the original's. Pure jnp: ``angle_deg`` may be
  traced (one compilation for every frame of a moving camera).

  Args:
    viewmat: (4, 4) world-to-camera matrix.
    center: (3,) a point on the axis.
    axis: (3,) axis direction (need not be unit).
    angle_deg: () turn [degrees].

  Returns:
    (4, 4) world-to-camera matrix.
  """
  viewmat = jnp.asarray(viewmat)
  dtype = jnp.result_type(viewmat.dtype, jnp.float32)
  k = _normalize(jnp.asarray(axis, dtype))
  c = jnp.asarray(center, dtype)
  a = jnp.deg2rad(jnp.asarray(angle_deg, dtype))
  K = jnp.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]],
                 [-k[1], k[0], 0.0]], dtype)
  R = jnp.eye(3, dtype=dtype) + jnp.sin(a) * K + (1 - jnp.cos(a)) * K @ K
  M = jnp.eye(4, dtype=dtype).at[:3, :3].set(R.T).at[:3, 3].set(c - R.T @ c)
  return viewmat.astype(dtype) @ M


def orbit_cameras(
  center,
  radius: float,
  elevation_deg: float,
  num: int,
  up=(0.0, 0.0, 1.0),
  fov_deg: float = 50.0,
  width: int = 256,
  height: int = 256,
  start_azimuth_deg: float = 0.0,
  near: float = 0.01,
  far: float = 1e10,
) -> list[Camera]:
  """``num`` cameras evenly spaced on a full circle, all looking at ``center``.

  Args:
    center: (3,) orbit centre and look-at target.
    radius: distance from ``center`` [scene units], > 0.
    elevation_deg: angle above the horizontal plane (perpendicular to ``up``).
    num: number of cameras (azimuth step ``360 / num`` degrees).
    up: world up.
    fov_deg: vertical field of view [degrees]; square pixels (fx = fy).
    width, height: image size [pixels].
    start_azimuth_deg: azimuth of the first camera (see
      :func:`orbit_position`).
    near, far: clipping depths.

  Returns:
    A list of ``num`` :class:`~physsplat_jax.types.Camera`, named
    ``orbit_0000``, ... .
  """
  _check_image(width, height, fov_deg)
  if not radius > 0:
    raise CameraError(f'orbit_cameras: radius must be > 0, got {radius}')
  if int(num) < 1:
    raise CameraError(f'orbit_cameras: num must be >= 1, got {num}')
  f = float(focal_from_fov(fov_deg, height))
  cams = []
  for i in range(int(num)):
    az = start_azimuth_deg + 360.0 * i / int(num)
    eye = orbit_position(center, radius, az, elevation_deg, up)
    vm = look_at(eye, np.asarray(center, np.float64), np.asarray(up, float))
    cams.append(
      make_camera(vm, f, f, width, height, near=near, far=far,
                  name=f'orbit_{i:04d}')
    )
  return cams


def _image_size(where, width, height) -> tuple[int, int]:
  """``(width, height)`` as ints, refusing anything but whole numbers >= 1."""
  out = []
  for label, v in (('width', width), ('height', height)):
    try:
      ok = float(v) >= 1 and int(v) == float(v)
    except (TypeError, ValueError, OverflowError):
      ok = False
    if not ok:
      raise CameraError(
        f'{where}: image {label}={v!r} must be a whole number of pixels '
        f'>= 1 (got {width!r}x{height!r})')
    out.append(int(v))
  return out[0], out[1]


def _check_image(width, height, fov_deg):
  if int(width) < 1 or int(height) < 1:
    raise CameraError(f'image size must be positive, got {width}x{height}')
  if not 0.0 < float(fov_deg) < 180.0:
    raise CameraError(f'fov_deg must be in (0, 180), got {fov_deg}')


# Beyond this many scene units a float32 view matrix cannot hold the
# scene (a camera fitted to 1e29 was "not a rigid transform").
MAX_FRAMED_EXTENT = 1e12


def framing_box(means) -> tuple[np.ndarray, np.ndarray]:
  """The box a fitted camera frames: the 1st-99th percentile box of the
  centres (robust to floaters), a unit box around them when they all sit
  at one point (one Gaussian: the fit needs an extent), a unit box at the
  origin when there are none.

  Raises:
    CameraError: a centre is not finite, or the box is too large to frame
      (positions off by many orders of magnitude: check the file's units).
  """
  m = np.asarray(means, np.float64).reshape(-1, 3)
  if not np.all(np.isfinite(m)):
    raise CameraError(
      f'cannot fit a camera: {int(np.sum(~np.isfinite(m).all(1)))} of '
      f'{len(m)} Gaussian centres are not finite; check the scene\'s file, '
      'or give a camera')
  if len(m) == 0:
    lo = hi = np.zeros(3)
  else:
    lo, hi = np.percentile(m, [1.0, 99.0], axis=0)
  if max(np.max(np.abs(lo)), np.max(np.abs(hi))) > MAX_FRAMED_EXTENT:
    raise CameraError(
      'cannot fit a camera to Gaussians whose centres span '
      f'({", ".join(f"{v:.3g}" for v in lo)}) to '
      f'({", ".join(f"{v:.3g}" for v in hi)}): beyond '
      f'{MAX_FRAMED_EXTENT:.0e} scene units; check the scene\'s positions '
      'and units, or give a camera')
  if not float(np.max(hi - lo)) > 0:
    # (fit_camera needs an extent: it failed in look_at, naming no file)
    lo, hi = lo - 0.5, hi + 0.5
  return lo, hi


def fit_camera(
  bounds_min,
  bounds_max,
  up=(0.0, 0.0, 1.0),
  width: int = 256,
  height: int = 256,
  fov_deg: float = 50.0,
  azimuth: float = 0.0,
  elevation: float = 20.0,
  padding: float = 1.1,
  near: float | None = None,
  far: float | None = None,
) -> Camera:
  """A camera that frames an axis-aligned box.

  The camera looks at the box centre from the given azimuth/elevation (see
  :func:`orbit_position`) at the distance where the box's bounding sphere,
  enlarged by ``padding``, just fits in the narrower field of view; so the
  whole box is visible from any direction.

  Args:
    bounds_min, bounds_max: (3,) box corners [scene units].
    up: world up.
    width, height: image size [pixels].
    fov_deg: vertical field of view [degrees] (square pixels).
    azimuth, elevation: viewing direction [degrees].
    padding: >= 1, extra margin around the bounding sphere.
    near, far: clipping depths; default to a range around the sphere.

  Returns:
    A :class:`~physsplat_jax.types.Camera`.
  """
  _check_image(width, height, fov_deg)
  lo = np.asarray(bounds_min, np.float64)
  hi = np.asarray(bounds_max, np.float64)
  if lo.shape != (3,) or hi.shape != (3,):
    raise CameraError(
      f'fit_camera: bounds must be (3,) vectors, got {lo.shape} and '
      f'{hi.shape}'
    )
  if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
    raise CameraError(f'fit_camera: non-finite bounds {lo} .. {hi}')
  if np.any(hi < lo):
    raise CameraError(
      f'fit_camera: bounds_max {hi} is below bounds_min {lo} on some axis'
    )
  if not padding >= 1.0:
    raise CameraError(f'fit_camera: padding must be >= 1, got {padding}')
  center = 0.5 * (lo + hi)
  r = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-9) * padding
  f = float(focal_from_fov(fov_deg, height))
  half = math.atan(min(width, height) / (2.0 * f))
  dist = r / math.sin(half)
  eye = orbit_position(center, dist, azimuth, elevation, up)
  vm = look_at(eye, center, np.asarray(up, float))
  near = max(dist - r, 1e-3 * dist) if near is None else near
  far = dist + r if far is None else far
  return make_camera(vm, f, f, width, height, near=near, far=far, name='fit')


def scene_camera(scene, width: int, height: int, index: int = 0) -> Camera:
  """A scene's camera brought to ``width x height``, or a fitted one.

  ``scene.cameras[index]`` keeps square pixels (the focal length follows
  the height; the principal point is re-centred when the aspect ratio
  changes). With ``index=-1`` or no cameras, a camera is fitted to the
  scene's Gaussians (1st-99th percentile box). The name is dropped and
  near/far are arrays (:meth:`Camera.unlabelled`), so views that differ
  only there compile once.

  Raises:
    ValueError: ``width``/``height`` not whole numbers >= 1, or ``index``
      not an integer in ``-1 .. len(scene.cameras) - 1`` (the message gives
      the range).
  """
  w, h = _image_size('scene_camera', width, height)
  try:
    index = operator.index(index)
  except TypeError:
    raise CameraError(
      f'scene_camera: camera_index={index!r} is not an integer; use '
      '0..N-1 for a scene camera or -1 for a fitted camera') from None
  if index < -1:
    n = len(scene.cameras)
    raise CameraError(
      f'camera_index={index}: negative indices other than -1 are not '
      f'supported; use 0..{n - 1} for one of scene {scene.name!r}\'s {n} '
      'cameras or -1 for a fitted camera')
  if index >= 0 and scene.cameras:
    if index >= len(scene.cameras):
      raise CameraError(
        f'camera_index={index} but scene {scene.name!r} has '
        f'{len(scene.cameras)} cameras; use 0..{len(scene.cameras) - 1} or -1 '
        'for a fitted camera.')
    c = scene.cameras[index]
    if abs(c.width / c.height - w / h) < 1e-6:
      cam = c.resized(w, h)
    else:
      s = h / c.height
      cam = c.replace(fx=c.fx * s, fy=c.fy * s,
                      cx=jnp.asarray(w / 2, c.fx.dtype), cy=c.cy * s,
                      width=w, height=h)
  else:
    m = np.asarray(scene.gaussians.means)
    lo, hi = np.percentile(m, 1, axis=0), np.percentile(m, 99, axis=0)
    cam = fit_camera(lo, hi, up=scene.up_vector, width=w, height=h,
                     azimuth=-60.0, elevation=25.0, padding=1.05)
  return cam.unlabelled()
