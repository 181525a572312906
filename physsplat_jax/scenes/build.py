"""Helpers shared by the built-in scenes: tubes, assembly, default cameras."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import trimesh

from physsplat_jax import cameras as _cameras
from physsplat_jax.types import Camera, Gaussians, ObjectInfo, Scene
from physsplat_jax.types import DataError
from physsplat_jax.types import concatenate_gaussians
from physsplat_jax.types import device_array

# Default image size and field of view of the built-in scenes' cameras.
DEFAULT_WIDTH = 384
DEFAULT_HEIGHT = 288
DEFAULT_FOV_DEG = 40.0
DEFAULT_NUM_CAMERAS = 8


def tube_mesh(points, radii, sections: int = 12) -> trimesh.Trimesh:
  """A closed, watertight tube along a polyline (branches, stems).

  Rings of ``sections`` vertices are placed around each polyline point in a
  frame carried along by parallel transport (no twisting), joined by quads
  and closed by a fan at each end.

  Args:
    points: (P, 3) centre line, P >= 2, consecutive points distinct.
    radii: (P,) radius at each point (> 0), or a scalar.
    sections: vertices per ring (>= 3).

  Returns:
    A watertight ``trimesh.Trimesh`` with outward normals.
  """
  pts = np.asarray(points, np.float64)
  if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2:
    raise DataError(f'tube_mesh: points must be (P>=2, 3), got {pts.shape}')
  r = np.broadcast_to(np.asarray(radii, np.float64), (len(pts),))
  if not np.all(r > 0):
    raise DataError('tube_mesh: radii must be > 0')
  seg = np.diff(pts, axis=0)
  if np.any(np.linalg.norm(seg, axis=-1) == 0):
    raise DataError('tube_mesh: consecutive points must differ')
  tang = np.concatenate([seg[:1], seg[:-1] + seg[1:], seg[-1:]])
  tang /= np.linalg.norm(tang, axis=-1, keepdims=True)
  helper = np.eye(3)[np.argmin(np.abs(tang[0]))]
  u = np.cross(tang[0], helper)
  u /= np.linalg.norm(u)
  rings = []
  theta = 2.0 * math.pi * np.arange(sections) / sections
  for i, t in enumerate(tang):
    u = u - t * (u @ t)  # parallel transport: drop the tangential part
    u /= np.linalg.norm(u)
    v = np.cross(t, u)
    rings.append(pts[i] + r[i] * (np.cos(theta)[:, None] * u
                                  + np.sin(theta)[:, None] * v))
  verts = np.concatenate(rings + [pts[:1], pts[-1:]])
  n, m = len(pts), sections
  faces = []
  for i in range(n - 1):
    for j in range(m):
      a, b = i * m + j, i * m + (j + 1) % m
      c, d = a + m, b + m
      faces += [[a, b, d], [a, d, c]]
  c0, c1 = n * m, n * m + 1
  for j in range(m):
    faces.append([c0, (j + 1) % m, j])
    faces.append([c1, (n - 1) * m + j, (n - 1) * m + (j + 1) % m])
  mesh = trimesh.Trimesh(verts, np.asarray(faces), process=True)
  mesh.fix_normals()
  return mesh


def assemble_scene(
  parts: Sequence[tuple[ObjectInfo, Gaussians]],
  *,
  cameras: Sequence[Camera] = (),
  up_axis: str = 'z',
  meters_per_unit: float = 1.0,
  name: str = '',
) -> Scene:
  """Concatenates per-object Gaussians into a :class:`Scene`.

  Args:
    parts: ``(ObjectInfo, Gaussians)`` pairs; object ``i`` gets id ``i``.
    cameras: the scene's cameras.
    up_axis: world up ('z', '-y', ...).
    meters_per_unit: metres per scene unit.
    name: scene label.

  Returns:
    The scene, ``object_ids`` (K,) int32.
  """
  if not parts:
    raise DataError('assemble_scene: no objects')
  ids = np.concatenate(
    [np.full(g.num, i, np.int32) for i, (_, g) in enumerate(parts)]
  )
  return Scene(
    gaussians=concatenate_gaussians([g for _, g in parts]),
    object_ids=device_array(ids),
    objects=tuple(o for o, _ in parts),
    cameras=tuple(cameras),
    up_axis=up_axis,
    meters_per_unit=float(meters_per_unit),
    name=name,
  )


def orbit_rig(
  center,
  radius: float,
  elevation_deg: float,
  *,
  num_cameras: int = DEFAULT_NUM_CAMERAS,
  width: int = DEFAULT_WIDTH,
  height: int = DEFAULT_HEIGHT,
  fov_deg: float = DEFAULT_FOV_DEG,
  start_azimuth_deg: float = 0.0,
  up=(0.0, 0.0, 1.0),
) -> tuple[Camera, ...]:
  """The default orbit camera set of a scene (OpenCV, looking at centre).

  ``near``/``far`` bracket the orbit sphere so that nothing in the scene is
  clipped.
  """
  if int(num_cameras) < 0:
    raise DataError(f'num_cameras must be >= 0, got {num_cameras}')
  if int(num_cameras) == 0:
    return ()
  return tuple(
    _cameras.orbit_cameras(
      center, radius, elevation_deg, int(num_cameras), up=up,
      fov_deg=fov_deg, width=int(width), height=int(height),
      start_azimuth_deg=start_azimuth_deg, near=0.01 * radius,
      far=100.0 * radius,
    )
  )


def check_detail(detail: float) -> float:
  """Validates the ``detail`` knob (spacings scale as ``1 / detail``)."""
  d = float(detail)
  if not 0.05 <= d <= 8.0:
    raise DataError(
      f'detail={detail} is out of range [0.05, 8]; 1 is the default, 2 '
      'gives about 4-8x more Gaussians'
    )
  return d
