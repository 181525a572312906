"""Scene frame <-> simulation frame (metres, +z up), and the render camera.

``x_sim = s R x_scene + shift``: ``R`` turns the scene's up axis to +z,
``s`` is ``scene.meters_per_unit`` and ``shift`` puts the simulated region
inside the grid ``[0, size]^3``. Everything user-facing (trajectories,
Gaussians, PLY frames) is given back in scene coordinates.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from physsplat_jax import cameras as cam_lib
from physsplat_jax import gaussians as gs
from physsplat_jax import struct
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


@jax.jit
def transform_gaussians(g: Gaussians, frame: SimFrame) -> Gaussians:
  """The same Gaussians expressed in the simulation frame (jitted: one
  program instead of a dozen eager ones, each compiled per shape)."""
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
  """The camera that renders the video (scene coordinates): see
  :func:`physsplat_jax.cameras.scene_camera`."""
  try:
    return cam_lib.scene_camera(scene, config.width, config.height,
                                config.camera_index)
  except ValueError as e:
    raise PipelineError(str(e)) from None
