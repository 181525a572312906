"""``ficus``: a ficus-like potted plant (the paper's flagship kind of scene).

Built in metres (``meters_per_unit = 1``), z up, the pot standing on
``z = 0``; about 0.6 m tall:

| object | shape | material | fixed |
|---|---|---|---|
| ``pot`` | hollow pot of revolution, 8 mm wall, rim | terracotta | yes |
| ``soil`` | fills the pot to 1.7 cm below the rim, mound | soil | yes |
| ``stem`` | tapered S-curved trunk, arching branches | plant_stem | no |
| ``leaves`` | ~280 curved, folded elliptic leaves | leaf | no |

The trunk starts 2.5 cm below the soil surface (rooted), branches leave it
at golden-angle azimuths; leaves sit along the outer 75 % of each branch and
around the crown, alternating sides, drooping, with per-leaf shades of green
(younger, lighter leaves towards the tips) and a lighter midrib. Leaves are
open sheets, so they get one layer of flat Gaussians and no interior.
"""

from __future__ import annotations

import math

import numpy as np
import trimesh

from physsplat_jax.scenes import build
from physsplat_jax.scenes.mesh import gaussians_from_mesh, rng_from_key
from physsplat_jax.types import ObjectInfo, Scene, concatenate_gaussians

# Pot geometry [m].
POT_BOTTOM_R, POT_TOP_R, POT_BODY_H = 0.074, 0.095, 0.150
RIM_R, RIM_TOP = 0.104, 0.175
WALL = 0.008
FLOOR = 0.012
SOIL_TOP = 0.158
# Plant geometry [m].
TRUNK_BASE, TRUNK_TOP = SOIL_TOP - 0.025, 0.50
NUM_BRANCHES = 10
LEAVES_PER_BRANCH = 26
CROWN_LEAVES = 24
UP = np.array([0.0, 0.0, 1.0])


def _outer_r(z):
  return POT_BOTTOM_R + (POT_TOP_R - POT_BOTTOM_R) * z / POT_BODY_H


def _pot_mesh() -> trimesh.Trimesh:
  """Cup-shaped solid of revolution: outer wall, rim, inner wall, floor."""
  zi = np.linspace(FLOOR, POT_BODY_H, 6)
  profile = (
    [(0.0, 0.0), (POT_BOTTOM_R - 0.003, 0.0), (POT_BOTTOM_R, 0.003),
     (POT_TOP_R, POT_BODY_H), (RIM_R, POT_BODY_H + 0.002),
     (RIM_R, RIM_TOP), (RIM_R - 0.004, RIM_TOP + 0.002),
     (_outer_r(POT_BODY_H) - WALL + 0.001, RIM_TOP)]
    + [(_outer_r(z) - WALL, z) for z in zi[::-1]]
    + [(0.0, FLOOR)]
  )
  mesh = trimesh.creation.revolve(np.asarray(profile), sections=48)
  mesh.fix_normals()
  return mesh


def _soil_mesh(rng) -> trimesh.Trimesh:
  """The soil: fills the pot from the floor to a slightly mounded top."""
  r_top = _outer_r(SOIL_TOP) - WALL - 0.0005
  r = np.linspace(0.0, 1.0, 8)
  z_top = SOIL_TOP + 0.006 * (1.0 - r**2)
  profile = np.concatenate([
    [[0.0, FLOOR + 0.0005], [_outer_r(FLOOR) - WALL - 0.0005, FLOOR + 0.0005]],
    np.stack([r[::-1] * r_top, z_top[::-1]], -1),
  ])
  mesh = trimesh.creation.revolve(profile, sections=48)
  v = np.asarray(mesh.vertices).copy()
  top = v[:, 2] > SOIL_TOP - 1e-4
  v[top, 2] += 0.002 * rng.normal(size=int(top.sum()))  # clods
  mesh = trimesh.Trimesh(v, mesh.faces, process=True)
  mesh.fix_normals()
  return mesh


def _trunk_points() -> np.ndarray:
  t = np.linspace(0.0, 1.0, 12)
  z = TRUNK_BASE + (TRUNK_TOP - TRUNK_BASE) * t
  x = 0.018 * np.sin(1.3 * math.pi * t) * t
  y = -0.010 * np.sin(2.0 * math.pi * t) * t
  return np.stack([x, y, z], -1)


def _along(points, t):
  """Point at arclength fraction ``t`` of a polyline (and its tangent)."""
  seg = np.diff(points, axis=0)
  length = np.linalg.norm(seg, axis=-1)
  cum = np.concatenate([[0.0], np.cumsum(length)])
  s = t * cum[-1]
  i = int(np.clip(np.searchsorted(cum, s) - 1, 0, len(seg) - 1))
  f = (s - cum[i]) / length[i]
  return points[i] + f * seg[i], seg[i] / length[i]


def _branches(rng, trunk):
  out = []
  for k in range(NUM_BRANCHES):
    frac = k / (NUM_BRANCHES - 1)
    h = 0.38 + 0.55 * frac + rng.uniform(-0.03, 0.03)
    start, _ = _along(trunk, h)
    phi = math.radians(137.5 * k + rng.uniform(-15, 15))
    out_dir = np.array([math.cos(phi), math.sin(phi), 0.0])
    elev = math.radians(rng.uniform(30, 50))
    length = (0.20 - 0.07 * frac) * rng.uniform(0.9, 1.1)
    droop = rng.uniform(0.35, 0.6)
    t = np.linspace(0.0, 1.0, 7)[:, None]
    pts = start + length * (
      t * math.cos(elev) * out_dir
      + UP * (math.sin(elev) * t - droop * t**2)
    )
    out.append(pts)
  return out


def _leaf(base, d, n, length, width, fold, curl, nu=7, nv=5):
  """Vertices (nu * nv, 3) and faces of one leaf (u along d, v across)."""
  e = np.cross(n, d)
  u = np.linspace(0.0, 1.0, nu)[:, None]
  v = np.linspace(-1.0, 1.0, nv)[None, :]
  half = 0.5 * width * np.sin(math.pi * u) ** 0.7 * (1.0 - 0.25 * u)
  off = (fold * np.abs(v) * half - curl * length * u**2)  # along n
  pts = (base + (u * length)[..., None] * d + (v * half)[..., None] * e
         + off[..., None] * n)
  idx = np.arange(nu * nv).reshape(nu, nv)
  a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
  c, dd = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
  faces = np.concatenate([np.stack([a, b, dd], -1), np.stack([a, dd, c], -1)])
  return pts.reshape(-1, 3), faces, np.broadcast_to(np.abs(v), (nu, nv))


def _leaves(rng, trunk, branches):
  """All leaves as one open mesh with per-vertex colours."""
  anchors = []  # (point, tangent, tip fraction)
  for pts in branches:
    ts = np.sort(rng.uniform(0.25, 1.0, LEAVES_PER_BRANCH))
    for i, t in enumerate(ts):
      p, tan = _along(pts, t)
      anchors.append((p, tan, t, 1.0 if i % 2 else -1.0))
  for i in range(CROWN_LEAVES):
    t = rng.uniform(0.85, 1.0)
    p, tan = _along(trunk, t)
    anchors.append((p, tan, 1.0, 1.0 if i % 2 else -1.0))
  verts, faces, cols = [], [], []
  old = np.array([0.12, 0.30, 0.08])
  young = np.array([0.30, 0.55, 0.14])
  rib = np.array([0.50, 0.62, 0.28])
  for p, tan, t, side in anchors:
    sidev = np.cross(tan, UP)
    if np.linalg.norm(sidev) < 1e-6:
      a = rng.uniform(0, 2 * math.pi)
      sidev = np.array([math.cos(a), math.sin(a), 0.0])
    sidev /= np.linalg.norm(sidev)
    d = (0.6 * tan + side * sidev - 0.45 * UP
         + 0.35 * rng.normal(size=3))
    d /= np.linalg.norm(d)
    n = UP + 0.45 * rng.normal(size=3)
    n = n - (n @ d) * d
    n /= np.linalg.norm(n)
    length = rng.uniform(0.045, 0.065)
    vtx, fc, across = _leaf(p + 0.006 * d, d, n, length, 0.42 * length,
                            fold=rng.uniform(0.1, 0.3),
                            curl=rng.uniform(0.05, 0.2))
    shade = np.clip(t + rng.normal(0.0, 0.2), 0.0, 1.0)
    green = (old * (1 - shade) + young * shade) * rng.uniform(0.85, 1.15)
    a = across.reshape(-1, 1)
    col = np.where(a < 0.3, 0.65 * green + 0.35 * rib, green * (1 - 0.12 * a))
    faces.append(fc + sum(len(x) for x in verts))
    verts.append(vtx)
    cols.append(col)
  mesh = trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces),
                         process=False)
  return mesh, np.clip(np.concatenate(cols), 0.0, 1.0)


def make_ficus(
  seed: int = 0,
  *,
  detail: float = 1.0,
  num_cameras: int = build.DEFAULT_NUM_CAMERAS,
  width: int = build.DEFAULT_WIDTH,
  height: int = build.DEFAULT_HEIGHT,
  fov_deg: float = build.DEFAULT_FOV_DEG,
) -> Scene:
  """The ``ficus`` scene: a potted plant.

  Args:
    seed: int seed or JAX PRNG key; same seed -> identical arrays (the seed
      also shapes the plant: branch angles, leaf placement).
    detail: Gaussian density; spacings scale as ``1 / detail``.
    num_cameras: orbit cameras to attach (0 for none).
    width, height: camera image size [pixels].
    fov_deg: vertical field of view [degrees].

  Returns:
    A :class:`~physsplat_jax.types.Scene` (metres, z up) with objects
    ``pot``, ``soil``, ``stem``, ``leaves``.
  """
  dt = build.check_detail(detail)
  rng = rng_from_key(seed)
  keys = rng.integers(1 << 62, size=8)
  shape_rng = np.random.default_rng(keys[0])

  pot = _pot_mesh()
  pot_g = gaussians_from_mesh(
    pot, keys[1], surface_spacing=0.007 / dt, interior_spacing=0.009 / dt,
    color=(0.72, 0.38, 0.24), color_noise=0.07, noise_scale=0.03,
    shading=0.3, smooth_angle_deg=35.0,
  )
  soil = _soil_mesh(shape_rng)
  soil_top = np.asarray(soil.face_normals)[:, 2] > 0.3
  soil_g = gaussians_from_mesh(
    soil, keys[2], surface_spacing=0.005 / dt, interior_spacing=0.015 / dt,
    face_mask=soil_top, color=(0.25, 0.17, 0.11), color_noise=0.25,
    noise_scale=0.008, shading=0.2,
  )

  trunk = _trunk_points()
  tubes = [build.tube_mesh(trunk, np.linspace(0.011, 0.004, len(trunk)))]
  branches = _branches(shape_rng, trunk)
  tubes += [build.tube_mesh(b, np.linspace(0.0045, 0.002, len(b)), 8)
            for b in branches]
  bark = lambda p, n: np.broadcast_to([0.36, 0.29, 0.20], (len(p), 3))
  stem_g = concatenate_gaussians([
    gaussians_from_mesh(
      t, int(keys[3]) + i, surface_spacing=0.004 / dt,
      interior_spacing=0.0045 / dt, color=bark, color_noise=0.1,
      noise_scale=0.01, shading=0.3,
    )
    for i, t in enumerate(tubes)
  ])

  leaves, leaf_colors = _leaves(shape_rng, trunk, branches)
  leaf_g = gaussians_from_mesh(
    leaves, keys[4], surface_spacing=0.0055 / dt, vertex_colors=leaf_colors,
    interior=False, opacity=0.97, thickness=0.12, color_noise=0.05,
    noise_scale=0.02, shading=0.35, smooth_angle_deg=60.0,
  )

  cams = build.orbit_rig(
    (0.0, 0.0, 0.30), 0.88, 15.0, num_cameras=num_cameras, width=width,
    height=height, fov_deg=fov_deg, start_azimuth_deg=-60.0,
  )
  return build.assemble_scene(
    [
      (ObjectInfo('pot', 'terracotta', fixed=True, tags=('support', 'base')),
       pot_g),
      (ObjectInfo('soil', 'soil', fixed=True, tags=('base',)), soil_g),
      (ObjectInfo('stem', 'plant_stem', tags=('plant',)), stem_g),
      (ObjectInfo('leaves', 'leaf', tags=('plant', 'foliage')), leaf_g),
    ],
    cameras=cams,
    up_axis='z',
    meters_per_unit=1.0,
    name='ficus',
  )
