"""Triangle meshes -> 3D Gaussians (the building block of the built-in scenes).

A mesh becomes two sets of Gaussians, as a 3DGS capture of a solid object
would look after internal filling:

* Surface Gaussians. The faces are sampled with density ``1 / s^2`` for a
  spacing ``s``: face ``f`` of area ``A_f`` gets ``floor(A_f / s^2 + u_f)``
  samples (``u_f`` uniform, so the expected count is exact), placed by a
  randomly shifted R2 low-discrepancy sequence (Roberts 2018) folded into the
  triangle, so large faces are covered evenly, without the clumps and holes
  of i.i.d. sampling. Each Gaussian is flat in the tangent plane: local axes
  ``(t1, t2, n)`` with ``t2 = n x t1`` (a proper rotation, ``t1`` at a random
  angle about ``n``) and standard deviations ``(a s, a s, thickness s)``,
  ``a = tangent_scale`` times a small log-normal jitter. ``n`` is the
  auto-smoothed normal: the corner normals average the adjacent faces within
  ``smooth_angle_deg`` of the face (Blender "auto smooth"), interpolated
  barycentrically, so spheres and cylinders look round and boxes keep sharp
  edges.
* Interior Gaussians (``interior=True``, watertight meshes only). Cell
  centres of a cubic lattice of spacing ``s_i`` (default ``1.5 s``),
  jittered by up to ``s_i / 4`` and kept where a vertical ray from them
  crosses the surface an odd number of times (:func:`interior_lattice`,
  vectorised per lattice column: ``trimesh``'s ``mesh.contains`` took
  ~10 s for 20k points here); isotropic with standard deviation
  ``interior_scale s_i``. They make the object solid when it is cut or
  deformed and give particle filling (:mod:`physsplat_jax.sampling`)
  something to start from.

Colour is SH degree 0. The base colour comes from one RGB, per-face or
per-vertex colours (interpolated), or a function of position and normal
(wood grain, labels, stripes). It is then shaded and varied so that the
object reads as a real material rather than flat CG::

  rgb = base * (1 - shading + shading (0.5 + 0.5 n.l))     surface only
            * (1 + color_noise (0.7 noise(x / noise_scale) + 0.3 eps))
            * interior_shade                                 interior only

with ``l`` a fixed light direction, ``noise`` a smooth unit-variance random
field (random Fourier features) and ``eps`` white noise. Interior Gaussians
take the base colour of their nearest surface sample.

Everything here runs on the host in NumPy (meshes are host objects) and is
deterministic for a given ``key`` (a JAX PRNG key or an int seed).
"""

from __future__ import annotations

import math
from typing import Callable

import jax
import numpy as np
import scipy
import trimesh

from physsplat_jax import gaussians as _g
from physsplat_jax.errors import PhysSplatError
from physsplat_jax.types import Gaussians
from physsplat_jax.types import device_array

ColorFn = Callable[[np.ndarray, np.ndarray], np.ndarray]

# R2 sequence constants: 1 / g and 1 / g^2 for the plastic number g.
_PLASTIC = 1.324717957244746
_R2 = np.array([1.0 / _PLASTIC, 1.0 / _PLASTIC**2])
# Random Fourier features in the smooth noise field.
_NOISE_FEATURES = 24
# Opacities are kept inside (0, 1) so the logit is finite.
_OPACITY_EPS = 1e-4


class MeshError(PhysSplatError, ValueError):
  """A mesh or an option that cannot be turned into Gaussians."""


def rng_from_key(key) -> np.random.Generator:
  """A NumPy generator seeded from a JAX PRNG key or an int seed."""
  if isinstance(key, (int, np.integer)):
    return np.random.default_rng(int(key))
  if isinstance(key, np.random.Generator):
    return key
  try:
    dtype = getattr(key, 'dtype', None)
    typed = dtype is not None and jax.dtypes.issubdtype(
      dtype, jax.dtypes.prng_key
    )
    words = np.asarray(jax.random.key_data(key) if typed else key)
    if words.dtype.kind not in 'iu' or words.size == 0:
      raise TypeError(words.dtype)
    words = words.astype(np.uint32).ravel()
  except (TypeError, ValueError) as e:
    raise MeshError(
      f'key must be a JAX PRNG key or an int seed, got {key!r}'
    ) from e
  return np.random.default_rng([int(w) for w in words])


def smooth_noise(
  points: np.ndarray, rng: np.random.Generator, scale: float,
  num_features: int = _NOISE_FEATURES,
) -> np.ndarray:
  """A smooth random field with zero mean and unit variance at ``points``.

  ``sqrt(2 / M) sum_m cos(w_m . x + b_m)`` with ``w_m ~ N(0, I / scale^2)``
  and ``b_m ~ U(0, 2 pi)`` (random Fourier features of a squared-exponential
  field with length scale ``scale``).

  Args:
    points: (P, 3) positions [scene units].
    rng: the generator (consumed).
    scale: correlation length [scene units], > 0.
    num_features: M.

  Returns:
    (P,) float64 values, roughly N(0, 1) each.
  """
  w = rng.normal(size=(num_features, 3)) / scale
  b = rng.uniform(0.0, 2.0 * math.pi, num_features)
  return math.sqrt(2.0 / num_features) * np.cos(points @ w.T + b).sum(-1)


def wood_grain(rng: np.random.Generator, light, dark, contrast: float):
  """A colour function ``color(points, normals)`` for wood grain along x.

  Streaks are :func:`smooth_noise` stretched 10x along x, mixing ``light``
  and ``dark`` RGB by ``0.5 + contrast * streak`` (clipped to [0, 1]).

  Args:
    rng: the generator; one integer is drawn to seed the grain's own.
    light, dark: (3,) RGB in [0, 1].
    contrast: how far the streaks move the mix from half-way.
  """
  field_rng = np.random.default_rng(rng.integers(1 << 62))
  light, dark = np.asarray(light), np.asarray(dark)

  def color(p, n):
    streak = smooth_noise(p * np.array([0.1, 1.0, 1.0]), field_rng, 0.02)
    t = np.clip(0.5 + contrast * streak, 0.0, 1.0)[:, None]
    return light * (1 - t) + dark * t

  return color


def _as_trimesh(mesh) -> trimesh.Trimesh:
  if not isinstance(mesh, trimesh.Trimesh):
    raise MeshError(
      f'mesh must be a trimesh.Trimesh, got {type(mesh).__name__} (a '
      'Scene or Path from trimesh.load? pass force="mesh")'
    )
  if len(mesh.faces) == 0:
    raise MeshError('mesh has no faces')
  v = np.asarray(mesh.vertices)
  if not np.all(np.isfinite(v)):
    raise MeshError('mesh has non-finite vertices')
  return mesh


def corner_normals(mesh: trimesh.Trimesh,
                   smooth_angle_deg: float = 40.0) -> np.ndarray:
  """Auto-smoothed normals at the three corners of every face.

  The normal of face ``f`` at its vertex ``v`` is the area-weighted mean of
  the normals of the faces around ``v`` that lie within ``smooth_angle_deg``
  of ``f``'s normal (so edges sharper than that stay sharp).

  Args:
    mesh: the mesh.
    smooth_angle_deg: smoothing threshold [degrees]; 0 gives face normals.

  Returns:
    (F, 3, 3) unit normals, ``[face, corner, xyz]``.
  """
  fn = np.asarray(mesh.face_normals, np.float64)
  if smooth_angle_deg <= 0:
    return np.repeat(fn[:, None, :], 3, axis=1)
  area = np.asarray(mesh.area_faces, np.float64)
  adj = np.asarray(mesh.vertex_faces)[np.asarray(mesh.faces)]  # (F, 3, D)
  valid = adj >= 0
  adj = np.where(valid, adj, 0)
  nb = fn[adj]  # (F, 3, D, 3)
  cos = np.einsum('fx,fcdx->fcd', fn, nb)
  w = np.where(valid & (cos >= math.cos(math.radians(smooth_angle_deg))),
               area[adj], 0.0)
  n = np.einsum('fcd,fcdx->fcx', w, nb)
  norm = np.linalg.norm(n, axis=-1, keepdims=True)
  return np.where(norm > 1e-12, n / np.maximum(norm, 1e-12), fn[:, None, :])


def sample_surface(
  mesh: trimesh.Trimesh, spacing: float, rng: np.random.Generator,
  face_mask=None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Stratified area sampling with density ``1 / spacing^2``.

  Args:
    mesh: the mesh.
    spacing: s [scene units].
    rng: NumPy generator (consumed).
    face_mask: optional (F,) bool; faces outside it get no samples.

  Returns:
    (points (P, 3), face_index (P,), barycentric (P, 3)).
  """
  tri = np.asarray(mesh.triangles, np.float64)  # (F, 3, 3)
  area = np.asarray(mesh.area_faces, np.float64)
  if face_mask is not None:
    face_mask = np.asarray(face_mask)
    if face_mask.shape != area.shape or face_mask.dtype != bool:
      raise MeshError(
        f'face_mask must be a ({len(area)},) bool array, got '
        f'{face_mask.dtype} {face_mask.shape}'
      )
    area = np.where(face_mask, area, 0.0)
  counts = np.floor(area / spacing**2 + rng.uniform(size=len(area)))
  counts = counts.astype(np.int64)
  face = np.repeat(np.arange(len(area)), counts)
  start = np.cumsum(counts) - counts
  k = np.arange(face.size) - np.repeat(start, counts)
  offset = rng.uniform(size=(len(area), 2))
  uv = np.mod(offset[face] + (k[:, None] + 1) * _R2, 1.0)
  fold = uv.sum(-1) > 1.0
  uv[fold] = 1.0 - uv[fold]
  bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], -1)
  points = np.einsum('pc,pcx->px', bary, tri[face])
  return points, face, bary


def interior_lattice(mesh: trimesh.Trimesh, spacing: float,
                     rng: np.random.Generator,
                     chunk: int = 1 << 21) -> np.ndarray:
  """Jittered lattice points inside a watertight mesh (ray parity).

  Cell centres of a lattice of ``spacing`` (centred in the bounding box) are
  jittered by up to ``spacing / 4`` (x, y per column, z per point, so that
  rays almost surely miss edges and vertices), and a point is inside when a
  ray from it along +z crosses the surface an odd number of times. All rays
  of a lattice column are the same line, so the cost is O(columns x faces),
  vectorised, instead of ``mesh.contains``'s per-point ray queries (which
  take seconds for a few thousand points).

  Args:
    mesh: a watertight mesh.
    spacing: lattice spacing [scene units].
    rng: NumPy generator (consumed).
    chunk: (column, face) pairs tested at once (bounds memory).

  Returns:
    (P, 3) float64 interior points.
  """
  lo, hi = np.asarray(mesh.bounds, np.float64)
  n = np.maximum(np.floor((hi - lo) / spacing).astype(np.int64), 1)
  pad = 0.5 * ((hi - lo) - n * spacing)
  ax = [lo[d] + pad[d] + (np.arange(n[d]) + 0.5) * spacing for d in range(3)]
  cx, cy = (a.ravel() for a in np.meshgrid(ax[0], ax[1], indexing='ij'))
  cols = np.stack([cx, cy], -1)
  cols += rng.uniform(-0.25, 0.25, cols.shape) * spacing
  tri = np.asarray(mesh.triangles, np.float64)
  a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
  # 2D barycentric set-up of each face's xy projection.
  e1, e2 = (b - a)[:, :2], (c - a)[:, :2]
  det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
  ok = np.abs(det) > 1e-18
  tmin, tmax = tri[:, :, :2].min(1), tri[:, :, :2].max(1)
  hit_col, hit_z = [], []
  step = max(1, chunk // max(len(tri), 1))
  for s0 in range(0, len(cols), step):
    p = cols[s0:s0 + step]  # (C, 2)
    inb = (np.all(p[:, None] >= tmin[None], -1)
           & np.all(p[:, None] <= tmax[None], -1) & ok[None])
    ci, fi = np.nonzero(inb)
    d = p[ci] - a[fi, :2]
    u = (d[:, 0] * e2[fi, 1] - d[:, 1] * e2[fi, 0]) / det[fi]
    v = (e1[fi, 0] * d[:, 1] - e1[fi, 1] * d[:, 0]) / det[fi]
    inside = (u >= 0) & (v >= 0) & (u + v <= 1)
    ci, fi, u, v = ci[inside], fi[inside], u[inside], v[inside]
    z = a[fi, 2] + u * (b[fi, 2] - a[fi, 2]) + v * (c[fi, 2] - a[fi, 2])
    hit_col.append(ci + s0)
    hit_z.append(z)
  hit_col = np.concatenate(hit_col)
  hit_z = np.concatenate(hit_z)
  # Sortable keys col + t with t in (0.25, 0.75) increasing in z.
  span = max(hi[2] - lo[2], 1e-12) * 4.0
  zkey = lambda z: 0.5 + (z - 0.5 * (lo[2] + hi[2])) / span
  keys = np.sort(hit_col + zkey(hit_z))
  pz = ax[2][None, :] + rng.uniform(-0.25, 0.25, (len(cols), n[2])) * spacing
  pcol = np.repeat(np.arange(len(cols)), n[2])
  pk = pcol + zkey(pz.ravel())
  above = np.searchsorted(keys, pcol + 1.0) - np.searchsorted(keys, pk)
  keep = (above % 2) == 1
  pts = np.concatenate(
    [np.repeat(cols, n[2], axis=0), pz.reshape(-1, 1)], axis=1
  )
  return pts[keep]


def _tangent_frames(normals: np.ndarray, rng) -> np.ndarray:
  """(P, 3, 3) rotations with columns ``(t1, t2, n)``, ``t1`` at random."""
  n = normals
  helper = np.eye(3)[np.argmin(np.abs(n), axis=-1)]
  t1 = np.cross(n, helper)
  t1 /= np.linalg.norm(t1, axis=-1, keepdims=True)
  t2 = np.cross(n, t1)
  theta = rng.uniform(0.0, 2.0 * math.pi, len(n))[:, None]
  a = np.cos(theta) * t1 + np.sin(theta) * t2
  b = np.cross(n, a)
  return np.stack([a, b, n], axis=-1)


def _base_colors(mesh, points, normals, face, bary, color, face_colors,
                 vertex_colors) -> np.ndarray:
  given = [x is not None for x in (color, face_colors, vertex_colors)]
  if sum(given) > 1:
    raise MeshError(
      'pass only one of color, face_colors and vertex_colors'
    )
  if face_colors is not None:
    fc = _rgb_array(face_colors, 'face_colors')
    if fc.shape != (len(mesh.faces), 3):
      raise MeshError(
        f'face_colors has shape {fc.shape}, expected ({len(mesh.faces)}, 3)'
      )
    return fc[face]
  if vertex_colors is not None:
    vc = _rgb_array(vertex_colors, 'vertex_colors')
    if vc.shape != (len(mesh.vertices), 3):
      raise MeshError(
        f'vertex_colors has shape {vc.shape}, expected '
        f'({len(mesh.vertices)}, 3)'
      )
    return np.einsum('pc,pcx->px', bary, vc[np.asarray(mesh.faces)[face]])
  if color is None:
    color = (0.6, 0.6, 0.6)
  if callable(color):
    out = np.asarray(color(points, normals), np.float64)
    if out.shape != (len(points), 3) or not np.all(np.isfinite(out)):
      raise MeshError(
        f'color function returned shape {out.shape} (or non-finite '
        f'values); expected finite ({len(points)}, 3) RGB'
      )
    return out
  rgb = _rgb_array(color, 'color')
  if rgb.shape != (3,):
    raise MeshError(
      f'color has shape {rgb.shape}; pass one RGB triple in [0, 1], or use '
      'face_colors / vertex_colors for per-element colours'
    )
  return np.broadcast_to(rgb, (len(points), 3))


def _rgb_array(x, what) -> np.ndarray:
  a = np.asarray(x, np.float64)
  if a.size and a.max() > 1.0 and np.issubdtype(np.asarray(x).dtype,
                                                np.integer):
    a = a / 255.0  # 8-bit colours (trimesh visuals)
  a = a[..., :3]
  if not np.all(np.isfinite(a)) or a.min(initial=0.0) < 0.0 or a.max(
    initial=0.0
  ) > 1.0:
    raise MeshError(f'{what} must hold RGB values in [0, 1] (or 0..255 ints)')
  return a


def _logit(p: float) -> float:
  p = min(max(float(p), _OPACITY_EPS), 1.0 - _OPACITY_EPS)
  return math.log(p / (1.0 - p))


def _check_mesh_options(positive, non_negative, light_dir):
  """Raises MeshError on a non-finite option, a non-positive scale
  (``positive``; None skipped), a negative amplitude (``non_negative``) or a
  zero / non-finite light direction."""
  for name, val in positive.items():
    if val is not None and not (math.isfinite(float(val)) and val > 0):
      raise MeshError(f'{name} must be finite and > 0, got {val}')
  for name, val in non_negative.items():
    if not (math.isfinite(float(val)) and val >= 0):
      raise MeshError(f'{name} must be finite and >= 0, got {val}')
  l = np.asarray(light_dir, np.float64)
  if l.shape != (3,) or not np.all(np.isfinite(l)) or not np.any(l):
    raise MeshError(f'light_dir must be a finite, non-zero 3-vector, got '
                    f'{np.asarray(light_dir).tolist()}')


def gaussians_from_mesh(
  mesh: trimesh.Trimesh,
  key,
  *,
  surface_spacing: float,
  color: tuple[float, float, float] | ColorFn | None = None,
  face_colors=None,
  vertex_colors=None,
  face_mask=None,
  interior: bool = True,
  interior_spacing: float | None = None,
  opacity: float = 0.95,
  interior_opacity: float | None = None,
  tangent_scale: float = 0.6,
  thickness: float = 0.1,
  interior_scale: float = 0.45,
  scale_jitter: float = 0.12,
  smooth_angle_deg: float = 40.0,
  color_noise: float = 0.06,
  noise_scale: float | None = None,
  shading: float = 0.25,
  light_dir=(0.35, -0.45, 1.0),
  interior_shade: float = 0.85,
  max_gaussians: int = 2_000_000,
  return_surface_mask: bool = False,
) -> Gaussians | tuple[Gaussians, np.ndarray]:
  """Gaussians on the surface (and inside) of a triangle mesh.

  See the module docstring for the construction. Units are those of the
  mesh vertices ("scene units").

  Args:
    mesh: a ``trimesh.Trimesh``; watertight if ``interior`` is True.
    key: JAX PRNG key or int seed; the result is a deterministic function
      of it.
    surface_spacing: s, mean distance between surface samples [scene
      units], > 0.
    color: one RGB in [0, 1], or ``f(points (P, 3), normals (P, 3)) ->
      (P, 3)`` RGB. Default grey. Exclusive with the two below.
    face_colors: (F, 3) RGB per face (floats in [0, 1] or 0..255 ints).
    vertex_colors: (V, 3) RGB per vertex, interpolated.
    face_mask: optional (F,) bool, the faces that get surface Gaussians
      (e.g. leave out the never-seen bottom of a table); the interior still
      uses the whole mesh.
    interior: also fill the inside (needs a watertight mesh).
    interior_spacing: s_i, lattice spacing inside; default ``1.5 s``.
    opacity: surface opacity in (0, 1).
    interior_opacity: opacity inside; default ``opacity``.
    tangent_scale: tangential standard deviation / s.
    thickness: normal standard deviation / s (flat splats: << 1).
    interior_scale: interior standard deviation / s_i.
    scale_jitter: standard deviation of the log-normal jitter of the
      tangential scales.
    smooth_angle_deg: normal smoothing threshold (see
      :func:`corner_normals`).
    color_noise: relative amplitude of the brightness variation.
    noise_scale: correlation length of the smooth variation; default
      ``6 s``.
    shading: strength of the baked light term in [0, 1].
    light_dir: (3,) direction towards the light (world frame of the mesh).
    interior_shade: brightness factor of interior Gaussians.
    max_gaussians: refuse (with a clear error) to build more than this.
    return_surface_mask: also return a (K,) bool mask of the surface
      Gaussians (they come first).

  Returns:
    :class:`~physsplat_jax.types.Gaussians` (float32, SH degree 0, no
    normals, no extras), or ``(gaussians, surface_mask)``.

  Raises:
    MeshError: bad mesh or option, non-watertight mesh with
      ``interior=True``, or too many Gaussians (message says which).
  """
  mesh = _as_trimesh(mesh)
  s = float(surface_spacing)
  if not s > 0 or not math.isfinite(s):
    raise MeshError(f'surface_spacing must be > 0, got {surface_spacing}')
  si = 1.5 * s if interior_spacing is None else float(interior_spacing)
  if interior and (not si > 0 or not math.isfinite(si)):
    raise MeshError(f'interior_spacing must be > 0, got {interior_spacing}')
  for name, val in (('opacity', opacity), ('interior_opacity',
                                           interior_opacity)):
    if val is not None and not 0.0 < float(val) < 1.0:
      raise MeshError(f'{name} must be in (0, 1), got {val}')
  if not 0.0 <= shading <= 1.0:
    raise MeshError(f'shading must be in [0, 1], got {shading}')
  _check_mesh_options(
    positive=dict(tangent_scale=tangent_scale, thickness=thickness,
                  interior_scale=interior_scale, noise_scale=noise_scale),
    non_negative=dict(scale_jitter=scale_jitter, color_noise=color_noise,
                      interior_shade=interior_shade),
    light_dir=light_dir)
  expected = float(mesh.area) / s**2
  if interior:
    if not mesh.is_watertight:
      raise MeshError(
        'interior=True needs a watertight mesh (inside is undefined '
        'otherwise): pass interior=False, or repair the mesh '
        '(trimesh.repair.fill_holes, mesh.merge_vertices())'
      )
    expected += abs(float(mesh.volume)) / si**3
  if expected > max_gaussians:
    raise MeshError(
      f'about {expected:.0f} Gaussians at surface_spacing={s:g} '
      f'(interior_spacing={si:g}) exceeds max_gaussians={max_gaussians}; '
      'raise the spacing'
    )
  rng = rng_from_key(key)
  noise_rng, jitter_rng = (np.random.default_rng(rng.integers(1 << 62))
                           for _ in range(2))

  # Surface.
  points, face, bary = sample_surface(mesh, s, rng, face_mask)
  if not len(points):
    raise MeshError(
      f'no surface Gaussians at surface_spacing={s:g}: the mesh (area '
      f'{float(mesh.area):.3g}) is smaller than the spacing, degenerate, or '
      'face_mask selects no face; lower surface_spacing or check the mesh')
  cn = corner_normals(mesh, smooth_angle_deg)
  normals = np.einsum('pc,pcx->px', bary, cn[face])
  normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True),
                        1e-12)
  frames = _tangent_frames(normals, rng)
  n_s = len(points)
  jit = np.exp(scale_jitter * rng.normal(size=(n_s, 2)))
  sig_s = np.concatenate(
    [tangent_scale * s * jit, np.full((n_s, 1), thickness * s)], axis=1
  )
  base_s = _base_colors(mesh, points, normals, face, bary, color,
                        face_colors, vertex_colors)
  l = np.asarray(light_dir, np.float64)
  l = l / np.linalg.norm(l)
  shade = 1.0 - shading + shading * (0.5 + 0.5 * normals @ l)
  rgb_s = base_s * shade[:, None]

  # Interior.
  inner = interior_lattice(mesh, si, jitter_rng) if interior else np.zeros(
    (0, 3))
  n_i = len(inner)
  if n_i:
    _, nearest = scipy.spatial.cKDTree(points).query(inner)
    rgb_i = base_s[nearest] * interior_shade
  else:
    rgb_i = np.zeros((0, 3))

  means = np.concatenate([points, inner])
  rgb = np.concatenate([rgb_s, rgb_i])
  field = smooth_noise(means, noise_rng,
                       6.0 * s if noise_scale is None else noise_scale)
  white = noise_rng.normal(size=(len(means), 3))
  rgb = rgb * (1.0 + color_noise * (0.7 * field[:, None] + 0.3 * white))
  rgb = np.clip(rgb, 0.0, 1.0)

  sig = np.concatenate([sig_s, np.full((n_i, 3), interior_scale * si)])
  rot = np.concatenate([frames, np.broadcast_to(np.eye(3), (n_i, 3, 3))])
  quats = scipy.spatial.transform.Rotation.from_matrix(rot).as_quat()
  quats = quats[:, [3, 0, 1, 2]]  # xyzw -> wxyz
  quats *= np.where(quats[:, :1] < 0, -1.0, 1.0)
  op_i = opacity if interior_opacity is None else interior_opacity
  logits = np.concatenate([np.full(n_s, _logit(opacity)),
                           np.full(n_i, _logit(op_i))])
  f32 = lambda a: device_array(a, np.float32)
  g = Gaussians(
    means=f32(means),
    log_scales=f32(np.log(sig)),
    quats=f32(quats),
    opacity_logits=f32(logits),
    sh=f32((rgb[:, None, :] - 0.5) / _g.SH_C0),  # INRIA RGB2SH
  )
  if return_surface_mask:
    return g, np.arange(len(means)) < n_s
  return g
