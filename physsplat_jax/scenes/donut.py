"""``donut``: a real captured 3DGS donut on a round wooden board.

The donut is ``physsplat_jax/data/scenes/donut.ply`` (45,624 Gaussians, SH
degree 0; source and MIT licence in ``physsplat_jax/data/README.md``), used
unchanged: same Gaussians, same coordinates. Its up axis is **+z**: the
object is flat in z (0.21 x 0.21 x 0.095 units, the smallest principal axis
is z), its base is a sharp plane at ``z ~ 0`` (1st percentile 0.0006 units)
and the bluish icing is on top (mean colour of the Gaussians above
``z = 0.07`` is (0.28, 0.43, 0.75), of those below ``z = 0.01`` the bready
(0.77, 0.72, 0.61)).

A real donut is about 9.5 cm across, so ``meters_per_unit = 0.45`` (the
donut is then 9.5 x 9.5 x 4.3 cm).

The support is a round wooden board (radius 0.16 units = 7.2 cm, 0.025
units thick) built from a cylinder mesh, centred under the donut, with its
top face ``GAP`` (0.001 units) below the lowest Gaussian centre of the donut,
near-transparent floaters included: the lowest centres (down to z = -0.0091)
have opacity < 0.01, the lowest with opacity > 0.05 is at z = -0.0006, so
the visible base hovers about 0.0085 units (3.8 mm) above the board.
"""

from __future__ import annotations

import os

import numpy as np
import trimesh

from physsplat_jax.scenes import build
from physsplat_jax.scenes.mesh import gaussians_from_mesh, rng_from_key
from physsplat_jax.scenes.mesh import wood_grain
from physsplat_jax.types import Gaussians, ObjectInfo, Scene

DONUT_PLY = os.path.join(
  os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
  'data', 'scenes', 'donut.ply',
)
METERS_PER_UNIT = 0.45
BOARD_RADIUS, BOARD_THICKNESS = 0.16, 0.025  # [scene units]
GAP = 0.001  # [scene units] between the board and the donut's lowest centre


def make_donut(
  seed: int = 0,
  *,
  detail: float = 1.0,
  num_cameras: int = build.DEFAULT_NUM_CAMERAS,
  width: int = build.DEFAULT_WIDTH,
  height: int = build.DEFAULT_HEIGHT,
  fov_deg: float = build.DEFAULT_FOV_DEG,
  donut: Gaussians | None = None,
) -> Scene:
  """The ``donut`` scene: the shipped real donut on a wooden board.

  Args:
    seed: int seed or JAX PRNG key (shapes only the board's Gaussians).
    detail: Gaussian density of the board (the donut is used as captured).
    num_cameras: orbit cameras to attach (0 for none).
    width, height: camera image size [pixels].
    fov_deg: vertical field of view [degrees].
    donut: the donut Gaussians; default: loaded from :data:`DONUT_PLY`.

  Returns:
    A :class:`~physsplat_jax.types.Scene` (``meters_per_unit`` 0.45, z up)
    with objects ``donut`` (dough) and ``wooden board`` (wood, fixed); the
    donut's Gaussians come first, unchanged.
  """
  d = build.check_detail(detail)
  if donut is None:
    from physsplat_jax.io.ply import load_ply  # the file is package data

    donut = load_ply(DONUT_PLY)
  keys = rng_from_key(seed).integers(1 << 62, size=3)
  m = np.asarray(donut.means, np.float64)
  lo, hi = m.min(0), m.max(0)
  center = 0.5 * (lo + hi)
  top = lo[2] - GAP
  board = trimesh.creation.cylinder(BOARD_RADIUS, BOARD_THICKNESS,
                                    sections=96)
  board.apply_translation((center[0], center[1], top - BOARD_THICKNESS / 2))
  board_g = gaussians_from_mesh(
    board, keys[0], surface_spacing=0.005 / d, interior_spacing=0.014 / d,
    face_mask=np.asarray(board.face_normals)[:, 2] > -0.5,  # no bottom
    color=wood_grain(np.random.default_rng(keys[1]), (0.72, 0.53, 0.33),
                     (0.55, 0.37, 0.21), 0.25), color_noise=0.05,
    opacity=0.98, shading=0.15, interior_scale=0.3, tangent_scale=0.75,
  )
  board_g = board_g.astype(donut.means.dtype)
  cams = build.orbit_rig(
    (center[0], center[1], top + 0.03), 0.55, 32.0,
    num_cameras=num_cameras, width=width, height=height, fov_deg=fov_deg,
    start_azimuth_deg=-60.0,
  )
  return build.assemble_scene(
    [
      (ObjectInfo('donut', 'dough', tags=('captured',)), donut),
      (ObjectInfo('wooden board', 'wood', fixed=True, tags=('support',)),
       board_g),
    ],
    cameras=cams,
    up_axis='z',
    meters_per_unit=METERS_PER_UNIT,
    name='donut',
  )
