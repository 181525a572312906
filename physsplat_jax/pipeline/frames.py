"""Scene frame <-> simulation frame (metres, +z up), and the render camera.

``x_sim = s R x_scene + shift``: ``R`` turns the scene's up axis to +z,
``s`` is ``scene.meters_per_unit`` and ``shift`` puts the simulated region
inside the grid ``[0, size]^3``. Everything user-facing (trajectories,
Gaussians, PLY frames) is given back in scene coordinates.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

from physsplat_jax import cameras as cam_lib
from physsplat_jax import gaussians as gs
from physsplat_jax.pipeline.config import PipelineError
from physsplat_jax.pipeline.config import PrepareConfig
from physsplat_jax.types import Array
from physsplat_jax.types import Camera
from physsplat_jax.types import Gaussians
from physsplat_jax.types import Scene


def up_rotation(up: np.ndarray) -> np.ndarray:
  """Proper rotation (3, 3) that maps the unit vector ``up`` to +z."""
  u = np.asarray(up, np.float64)
  u = u / np.linalg.norm(u)
  z = np.array([0.0, 0.0, 1.0])
  c = float(u @ z)
  if c > 1 - 1e-12:
    return np.eye(3)
  if c < -1 + 1e-12:
    return np.diag([1.0, -1.0, -1.0])  # 180 degrees about x
  v = np.cross(u, z)
  s = np.linalg.norm(v)
  vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
  return np.eye(3) + vx + vx @ vx * ((1 - c) / s**2)


class SimFrame(struct.PyTreeNode):
  """``x_sim = scale * rotation @ x_scene + shift`` (metres, +z up).

  Attributes:
    rotation: (3, 3) proper rotation (scene up -> +z).
    scale: () metres per scene unit.
    shift: (3,) [m].
  """

  rotation: Array
  scale: Array
  shift: Array

  def to_sim(self, x: Array) -> Array:
    return self.scale * (x @ self.rotation.T) + self.shift

  def to_scene(self, x: Array) -> Array:
    return ((x - self.shift) / self.scale) @ self.rotation

  def vector_to_sim(self, v: Array) -> Array:
    """Directions/velocities in scene axes [m/s] -> simulation axes."""
    return v @ self.rotation.T

  def covariance_to_scene(self, cov: Array) -> Array:
    R = self.rotation
    return (R.T @ cov @ R) / self.scale**2

  def rotation_to_scene(self, rot: Array) -> Array:
    R = self.rotation
    return R.T @ rot @ R


def transform_gaussians(g: Gaussians, frame: SimFrame) -> Gaussians:
  """The same Gaussians expressed in the simulation frame."""
  q = gs.rotmat_to_quat(jnp.asarray(frame.rotation, g.quats.dtype))
  quats = gs.quat_multiply(jnp.broadcast_to(q, g.quats.shape),
                           gs.normalize_quat(g.quats))
  return g.replace(
    means=frame.to_sim(g.means).astype(g.means.dtype),
    log_scales=(g.log_scales + jnp.log(frame.scale)).astype(
      g.log_scales.dtype),
    quats=quats.astype(g.quats.dtype),
  )


def render_camera(scene: Scene, config: PrepareConfig) -> Camera:
  """The camera that renders the video (scene coordinates).

  ``scene.cameras[config.camera_index]`` brought to ``width x height``
  (square pixels kept: the focal length follows the height, the principal
  point is re-centred when the aspect ratio changes), or, with
  ``camera_index=-1`` or no cameras, a camera fitted to the whole scene.
  """
  w, h = config.width, config.height
  cam = _render_camera(scene, config, w, h)
  # near/far are static fields of Camera: quantise them (near down, far up,
  # 3 significant digits) so equal views compile once.
  lo = lambda v: float(f'{v * (1 - 1e-3):.3g}')  # noqa: E731
  hi = lambda v: float(f'{v * (1 + 1e-3):.3g}')  # noqa: E731
  return cam.replace(near=lo(cam.near), far=hi(cam.far), name='')


def _render_camera(scene: Scene, config: PrepareConfig, w: int, h: int):
  if config.camera_index >= 0 and scene.cameras:
    if config.camera_index >= len(scene.cameras):
      raise PipelineError(
        f'camera_index={config.camera_index} but scene {scene.name!r} has '
        f'{len(scene.cameras)} cameras; use 0..{len(scene.cameras) - 1} or -1 '
        'for a fitted camera.')
    c = scene.cameras[config.camera_index]
    if abs(c.width / c.height - w / h) < 1e-6:
      return c.resized(w, h)
    s = h / c.height
    return c.replace(fx=c.fx * s, fy=c.fy * s, cx=jnp.asarray(w / 2, c.fx.dtype),
                     cy=c.cy * s, width=w, height=h)
  m = np.asarray(scene.gaussians.means)
  lo, hi = np.percentile(m, 1, axis=0), np.percentile(m, 99, axis=0)
  return cam_lib.fit_camera(lo, hi, up=scene.up_vector, width=w, height=h,
                            azimuth=-60.0, elevation=25.0, padding=1.05)
