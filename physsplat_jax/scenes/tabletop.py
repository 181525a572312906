"""``tabletop``: four objects of different materials on a wooden table top.

Built in metres (``meters_per_unit = 1``), z up, the table's top face at
``z = 0``:

| object | shape | size | material | fixed |
|---|---|---|---|---|
| ``table top`` | box | 0.60 x 0.40 x 0.03 m | wood | yes |
| ``jelly cube`` | box | 5 cm | jelly | no |
| ``rubber ball`` | sphere | 6 cm diameter | rubber | no |
| ``sand pile`` | rounded, uneven cone | 10 cm base, ~3 cm high | sand | no |
| ``metal can`` | cylinder | 6.6 cm x 12.2 cm (a 355 ml can) | aluminum | no |

The movable objects' lowest points lie ``GAP`` (2 mm) above the table and
their horizontal bounding boxes are at least 6.7 cm apart, so they can fall,
bounce and spread without touching at once. The jelly is drawn translucent
(lower opacity, brighter interior), the can has a red label, a white band
and silver ends, the ball a yellow stripe (so its rotation shows), the table
wood streaks.
"""

from __future__ import annotations

import numpy as np
import trimesh

from physsplat_jax.scenes import build
from physsplat_jax.scenes.mesh import gaussians_from_mesh, rng_from_key
from physsplat_jax.scenes.mesh import smooth_noise, wood_grain
from physsplat_jax.types import ObjectInfo, Scene

TABLE_SIZE = (0.60, 0.40, 0.03)  # [m]
GAP = 0.002  # [m] between the table and the movable objects' lowest points
# Horizontal centres of the movable objects [m].
LAYOUT = {
  'jelly cube': (-0.17, -0.05),
  'rubber ball': (-0.04, 0.09),
  'sand pile': (0.08, -0.07),
  'metal can': (0.19, 0.08),
}
JELLY_EDGE = 0.05
BALL_RADIUS = 0.03
SAND_RADIUS, SAND_HEIGHT = 0.05, 0.035
CAN_RADIUS, CAN_HEIGHT = 0.033, 0.122



def _ball_color(center):
  blue = np.array([0.13, 0.33, 0.80])
  yellow = np.array([0.98, 0.80, 0.15])
  axis = np.array([0.35, 0.0, 0.94])
  axis = axis / np.linalg.norm(axis)

  def color(p, n):
    d = p - center
    d = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
    stripe = np.abs(d @ axis) < 0.22
    return np.where(stripe[:, None], yellow, blue)

  return color


def _can_color(z0, p_axis):
  red = np.array([0.78, 0.07, 0.10])
  white = np.array([0.93, 0.93, 0.92])
  silver = np.array([0.62, 0.63, 0.66])

  def color(p, n):
    h = p[:, 2] - z0
    side = np.abs(n[:, 2]) < 0.5
    label = side & (h > 0.012) & (h < CAN_HEIGHT - 0.014)
    band = label & (np.abs(h - 0.55 * CAN_HEIGHT) < 0.008)
    rim = ~side & (np.linalg.norm(p[:, :2] - p_axis, axis=-1)
                   > CAN_RADIUS - 0.004)
    out = np.where(label[:, None], red, silver)
    out = np.where(rim[:, None], 0.8 * silver, out)
    out = np.where(band[:, None], white, out)
    # A vertical highlight, as a brushed cylinder shows it.
    spec = np.clip(n @ np.array([0.6, -0.8, 0.0]), 0.0, 1.0) ** 8
    return np.clip(out + 0.3 * spec[:, None], 0.0, 1.0)

  return color


def _sand_mesh(rng) -> trimesh.Trimesh:
  """A rounded cone of revolution with slightly uneven slopes."""
  r = np.linspace(0.0, 1.0, 14)
  # Concave foot, rounded top: z = H (1 - r^1.25) smoothed near the apex.
  z = SAND_HEIGHT * (1.0 - r**1.25) * (1.0 - 0.25 * np.exp(-(r / 0.12) ** 2))
  profile = np.concatenate([[[0.0, 0.0]], np.stack([r * SAND_RADIUS, z],
                                                    -1)[::-1]])
  mesh = trimesh.creation.revolve(profile, sections=40)
  v = np.asarray(mesh.vertices).copy()
  bump = smooth_noise(v, rng, 0.02)
  rad = np.linalg.norm(v[:, :2], axis=-1)
  # Radial unevenness, zero on the axis and on the base.
  v[:, :2] *= (1.0 + 0.05 * bump * (v[:, 2] > 1e-6)
               * np.minimum(rad / SAND_RADIUS * 4, 1))[:, None]
  mesh = trimesh.Trimesh(v, mesh.faces, process=True)
  mesh.fix_normals()
  return mesh


def make_tabletop(
  seed: int = 0,
  *,
  detail: float = 1.0,
  num_cameras: int = build.DEFAULT_NUM_CAMERAS,
  width: int = build.DEFAULT_WIDTH,
  height: int = build.DEFAULT_HEIGHT,
  fov_deg: float = build.DEFAULT_FOV_DEG,
) -> Scene:
  """The ``tabletop`` scene (the default demo scene).

  Args:
    seed: int seed or JAX PRNG key; same seed -> identical arrays.
    detail: Gaussian density; spacings scale as ``1 / detail`` (about 15k
      Gaussians at 1).
    num_cameras: orbit cameras to attach (0 for none).
    width, height: camera image size [pixels].
    fov_deg: vertical field of view [degrees].

  Returns:
    A :class:`~physsplat_jax.types.Scene` (metres, z up) with objects
    ``table top``, ``jelly cube``, ``rubber ball``, ``sand pile``,
    ``metal can``.
  """
  d = build.check_detail(detail)
  rng = rng_from_key(seed)
  keys = rng.integers(1 << 62, size=8)
  s_obj, si_obj = 0.0035 / d, 0.005 / d
  lx, ly, lz = TABLE_SIZE

  table = trimesh.creation.box((lx, ly, lz))
  table.apply_translation((0.0, 0.0, -lz / 2))
  table_g = gaussians_from_mesh(
    table, keys[0], surface_spacing=0.007 / d, interior_spacing=0.02 / d,
    face_mask=np.asarray(table.face_normals)[:, 2] > -0.5,  # no bottom
    color=wood_grain(np.random.default_rng(keys[1]), (0.66, 0.45, 0.27),
                     (0.50, 0.31, 0.17), 0.35), color_noise=0.05,
    opacity=0.98, shading=0.15, interior_scale=0.3, tangent_scale=0.75,
  )

  cx, cy = LAYOUT['jelly cube']
  jelly = trimesh.creation.box((JELLY_EDGE,) * 3)
  jelly.apply_translation((cx, cy, GAP + JELLY_EDGE / 2))
  jelly_g = gaussians_from_mesh(
    jelly, keys[2], surface_spacing=s_obj, interior_spacing=si_obj,
    color=(0.95, 0.25, 0.38), opacity=0.3, interior_opacity=0.12,
    interior_shade=1.1, color_noise=0.05, shading=0.2,
  )

  cx, cy = LAYOUT['rubber ball']
  center = np.array([cx, cy, GAP + BALL_RADIUS])
  ball = trimesh.creation.icosphere(4, BALL_RADIUS)
  ball.apply_translation(center)
  ball_g = gaussians_from_mesh(
    ball, keys[3], surface_spacing=s_obj, interior_spacing=si_obj,
    color=_ball_color(center), color_noise=0.04, shading=0.3,
  )

  cx, cy = LAYOUT['sand pile']
  sand = _sand_mesh(np.random.default_rng(keys[4]))
  sand.apply_translation((cx, cy, GAP))
  sand_g = gaussians_from_mesh(
    sand, keys[5], surface_spacing=s_obj, interior_spacing=si_obj,
    color=(0.80, 0.67, 0.45), color_noise=0.14, noise_scale=0.01,
    shading=0.3, smooth_angle_deg=60.0,
  )

  cx, cy = LAYOUT['metal can']
  can = trimesh.creation.cylinder(CAN_RADIUS, CAN_HEIGHT, sections=48)
  can.apply_translation((cx, cy, GAP + CAN_HEIGHT / 2))
  can_g = gaussians_from_mesh(
    can, keys[6], surface_spacing=s_obj, interior_spacing=si_obj * 1.4,
    color=_can_color(GAP, np.array([cx, cy])), color_noise=0.03, shading=0.35,
  )

  cams = build.orbit_rig(
    (0.01, 0.01, 0.03), 0.62, 30.0, num_cameras=num_cameras, width=width,
    height=height, fov_deg=fov_deg, start_azimuth_deg=-70.0,
  )
  return build.assemble_scene(
    [
      (ObjectInfo('table top', 'wood', fixed=True, tags=('support',)),
       table_g),
      (ObjectInfo('jelly cube', 'jelly'), jelly_g),
      (ObjectInfo('rubber ball', 'rubber'), ball_g),
      (ObjectInfo('sand pile', 'sand', tags=('granular',)), sand_g),
      (ObjectInfo('metal can', 'aluminum'), can_g),
    ],
    cameras=cams,
    up_axis='z',
    meters_per_unit=1.0,
    name='tabletop',
  )
