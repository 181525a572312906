"""PhysGaussian's render camera: a dataset camera, or a (moving) orbit.

As PhysGaussian's ``get_camera_view`` (``utils/camera_view_utils.py``):

- ``default_camera_index >= 0``: that camera of the scene (its
  ``cameras.json``), fixed;
- ``default_camera_index == -1``: a camera on a sphere around the viewpoint
  centre. The centre is ``mpm_space_viewpoint_center`` and the vertical
  ``v`` is ``mpm_space_vertical_upward_axis``, both mapped from the
  normalised domain back to the scene (``denormalise``). The horizontal
  axes are ``h1`` = (1, 1, 1) made orthogonal to ``v`` ((0.72, 0.37,
  -0.67) when (1, 1, 1) is nearly parallel to it) and ``h2 = h1 x v``. The
  camera sits at ``centre + r (cos e cos a h1 + cos e sin a h2 + sin e v)``
  and looks at the centre with ``v`` up in the image, where, at frame
  ``f``, ``a = init_azimuthm + f delta_a``, ``e = init_elevation + f
  delta_e`` and ``r = init_radius + f delta_r`` when ``move_camera`` is on
  (else the ``init_`` values) [degrees, degrees, scene units]. Intrinsics
  are those of the scene's first camera (PhysGaussian's ``data[0]``).

``show_hint`` makes PhysGaussian print the default camera's azimuth,
elevation and radius in this frame and exit; here :func:`camera_hint`
gives them (logged and written to ``report.json``) and the run goes on.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from physsplat_jax import cameras as cam_lib
from physsplat_jax.physgaussian.schema import ConfigError
from physsplat_jax.physgaussian.schema import PhysGaussianConfig
from physsplat_jax.types import Camera


def local_frame(vertical) -> np.ndarray:
  """(3, 3) columns ``(h1, h2, v)``: PhysGaussian's observer axes."""
  v = np.asarray(vertical, np.float64)
  v = v / np.linalg.norm(v)
  h1 = np.array([1.0, 1.0, 1.0])
  if abs(float(h1 @ v)) < 0.01:
    h1 = np.array([0.72, 0.37, -0.67])
  h1 = h1 - (h1 @ v) * v
  h1 /= np.linalg.norm(h1)
  return np.column_stack([h1, np.cross(h1, v), v])


def viewpoint(config: PhysGaussianConfig, transform
              ) -> tuple[np.ndarray, np.ndarray]:
  """(centre (3,), observer axes (3, 3)) in scene coordinates.

  Args:
    config: parsed config (its camera block).
    transform: ``(R, c, s)`` of the normalisation
      (:func:`physsplat_jax.physgaussian.driver.transform_host`).
  """
  R, c, s = transform

  def scene(xn):
    return ((np.asarray(xn, np.float64) - 1.0) / s + c) @ R

  cam = config.camera
  centre = scene(cam.viewpoint_center)
  up = scene(np.add(cam.viewpoint_center, cam.vertical_upward_axis)) - centre
  return centre, local_frame(up)


def orbit_position(azimuth, elevation, radius, centre, axes) -> np.ndarray:
  """Camera centre on the sphere (degrees, degrees, scene units)."""
  a, e = math.radians(azimuth), math.radians(elevation)
  local = radius * np.array([math.cos(a) * math.cos(e),
                             math.sin(a) * math.cos(e), math.sin(e)])
  return np.asarray(centre, np.float64) + axes @ local


def frame_angles(config: PhysGaussianConfig, frame: int
                 ) -> tuple[float, float, float]:
  """(azimuth, elevation, radius) of the orbit camera at ``frame``."""
  cam = config.camera
  f = frame if cam.move_camera else 0
  return (cam.init_azimuth + f * cam.delta_a,
          cam.init_elevation + f * cam.delta_e,
          cam.init_radius + f * cam.delta_r)


def frame_camera(config: PhysGaussianConfig, base: Camera, centre, axes,
                 frame: int) -> Camera:
  """The orbit camera of ``frame`` (``base`` gives the intrinsics).

  Raises:
    ConfigError: the radius is not positive at this frame.
  """
  a, e, r = frame_angles(config, frame)
  if not r > 0:
    raise ConfigError(
      f'{config.source}: the camera radius init_radius + frame * delta_r = '
      f'{r} at frame {frame} is not > 0; set init_radius > 0 (and a '
      'delta_r that keeps it positive), or default_camera_index >= 0 for a '
      'dataset camera.')
  eye = orbit_position(a, e, r, centre, axes)
  vm = cam_lib.look_at(eye, np.asarray(centre, np.float64), axes[:, 2])
  return base.replace(viewmat=jnp.asarray(vm, base.viewmat.dtype))


def camera_hint(camera: Camera, centre, axes) -> dict:
  """(radius, azimuth, elevation) of ``camera`` about the viewpoint, as
  PhysGaussian's ``show_hint`` prints them (to reuse as ``init_*``)."""
  d = np.asarray(camera.position, np.float64) - np.asarray(centre)
  r = float(np.linalg.norm(d))
  v, h1, h2 = axes[:, 2], axes[:, 0], axes[:, 1]
  dot = float(d @ v)
  elev = 90.0 - math.degrees(math.acos(np.clip(dot / r, -1.0, 1.0)))
  hor = d - dot * v
  n = float(np.linalg.norm(hor))
  az = math.degrees(math.acos(np.clip(float(hor @ h1) / n, -1.0, 1.0))) \
    if n > 0 else 0.0
  if float(hor @ h2) <= 0:
    az = -az
  return dict(init_azimuthm=az, init_elevation=elev, init_radius=r)
