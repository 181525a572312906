"""Deterministic synthetic objects with ground-truth material fields.

Training data for MPDP without Physics3D: procedural objects whose
heterogeneous property fields follow documented rules. Four families, all
with gravity along -z and a random yaw about z:

- ``beam``: a horizontal cantilever of tapered rectangular section, clamped at
  its root (x = 0); thickness falls linearly from root to tip.
- ``plant``: a slightly tapered vertical stem rooted at z = 0 with 2-5 thin
  elliptical leaves attached along it (tip points outward and upward).
- ``stack``: 2-4 boxes / spheres / cylinders stacked on the ground.
- ``blob``: a union of 3-6 overlapping spheres resting on the ground.

Each point carries a geodesic-ish distance ``d`` to the support (along the
beam; height above ground for stacks/blobs; along stem then leaf for plants)
and a local thickness ``t`` (smallest cross-section extent of the primitive
at that point; leaf rims floored at half the leaf's centre thickness). With
``d_n = d / max d`` and ``t_n = clip(log(t / geomean t), -1.5, 1.5)``:

  log m_E   = s * (A_D * (0.5 - d_n) + A_T * t_n)      stiffer near support,
                                                       in thick parts
  log m_nu  = s * (-B_D * (0.5 - d_n))                  slightly lower nu at
                                                       the stiff root
  log m_rho = s * C_T * t_n                             denser in thick parts

  s = clip(1 + 0.3 * (6 - log10 E_mean), 0.4, 1.6)   (softer -> stronger
      gradients), s = 0 for rigid objects and fluids ('newtonian', 'bingham')

and each field is divided by its mean over valid points (mean exactly 1), so
``E_i = E_mean * m_E_i`` as in MPDP. A_D = 1.2, A_T = 0.8, B_D = 0.15,
C_T = 0.3.

Everything is NumPy on the host and seeded (``numpy.random.default_rng``), so
the same seed gives bit-identical objects.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from physsplat_jax.mpdp import model as model_lib
from physsplat_jax.mpdp.model import MPDPError

KINDS = ('beam', 'plant', 'stack', 'blob')
A_D, A_T, B_D, C_T = 1.2, 0.8, 0.15, 0.3
T_CLIP = 1.5
FLUIDS = ('newtonian', 'bingham')
# Material models drawn for synthetic objects (with weights).
_MODELS = ('fixed_corotated', 'neo_hookean', 'stvk', 'von_mises',
           'plasticine', 'foam', 'snow', 'rigid', 'newtonian')
_MODEL_P = np.array([4, 2, 1, 1, 1, 1, 1, 1, 1], np.float64)


@dataclasses.dataclass(frozen=True)
class SyntheticObject:
  """One object (host NumPy arrays).

  Attributes:
    points: (N, 3) float32 positions [m]; padded rows are zero.
    mask: (N,) bool, True for the valid points.
    field: (N, 3) float32 ground-truth multipliers (E, nu, rho); valid mean 1.
    E, nu, rho: mean properties [Pa, -, kg/m^3].
    model: constitutive-model name.
    kind: object family (one of KINDS).
    dist: (N,) float32 distance to the support [m] (0 for padding).
    thickness: (N,) float32 local thickness [m] (0 for padding).
  """

  points: np.ndarray
  mask: np.ndarray
  field: np.ndarray
  E: float
  nu: float
  rho: float
  model: str
  kind: str
  dist: np.ndarray
  thickness: np.ndarray

  @property
  def means(self):
    """(MEANS_DIM,) encoded means for :func:`model.predict`."""
    return model_lib.encode_means(self.E, self.nu, self.rho, self.model)


def _beam(rng, n):
  length = rng.uniform(1.5, 3.0)
  w0 = rng.uniform(0.12, 0.3)
  h0 = w0 * rng.uniform(0.8, 1.6)
  taper = rng.uniform(0.2, 0.6)
  pts = []
  while sum(len(p) for p in pts) < n:
    c = rng.uniform([0, -w0, -h0], [length, w0, h0], size=(4 * n, 3))
    f = 1.0 - (1.0 - taper) * c[:, 0] / length
    ok = (np.abs(c[:, 1]) <= w0 * f) & (np.abs(c[:, 2]) <= h0 * f)
    pts.append(c[ok])
  p = np.concatenate(pts)[:n]
  f = 1.0 - (1.0 - taper) * p[:, 0] / length
  thick = 2.0 * np.minimum(w0, h0) * f
  p[:, 2] += h0 + 0.5
  return p, p[:, 0].copy(), thick


def _plant(rng, n):
  height = rng.uniform(1.0, 2.0)
  r0 = rng.uniform(0.04, 0.08)
  num_leaves = int(rng.integers(2, 6))
  n_stem = n * 2 // 5
  counts = np.full(num_leaves, (n - n_stem) // num_leaves)
  counts[: (n - n_stem) - counts.sum()] += 1
  # Stem: cylinder with radius tapering to 60% at the top.
  z = rng.uniform(0, height, n_stem)
  r = r0 * (1.0 - 0.4 * z / height)
  ang = rng.uniform(0, 2 * np.pi, n_stem)
  rad = r * np.sqrt(rng.uniform(0, 1, n_stem))
  stem = np.stack([rad * np.cos(ang), rad * np.sin(ang), z], -1)
  pts, dist, thick = [stem], [z], [2 * r]
  for c in counts:
    za = rng.uniform(0.3, 0.95) * height
    ra = r0 * (1.0 - 0.4 * za / height)
    a = rng.uniform(0.25, 0.6)            # half-length
    b = a * rng.uniform(0.25, 0.5)        # half-width
    cth = rng.uniform(0.01, 0.025)        # half-thickness at the centre
    yaw = rng.uniform(0, 2 * np.pi)
    pitch = rng.uniform(0.1, 0.7)
    # Uniform samples in the ellipse, then thickness from the ellipsoid.
    u = rng.uniform(-1, 1, (4 * c, 2))
    u = u[np.sum(u * u, -1) <= 1.0][:c]
    while len(u) < c:
      v = rng.uniform(-1, 1, (4 * c, 2))
      u = np.concatenate([u, v[np.sum(v * v, -1) <= 1.0]])[:c]
    half = cth * np.sqrt(np.maximum(1.0 - np.sum(u * u, -1), 0.0))
    w = rng.uniform(-1, 1, c) * half
    # Local frame: leaf axis along x' (from the stem outward), width y'.
    s = (u[:, 0] + 1.0) * a               # distance from the attachment
    local = np.stack([s, u[:, 1] * b, w], -1)
    cp, sp = np.cos(pitch), np.sin(pitch)
    rot_p = np.array([[cp, 0, -sp], [0, 1, 0], [sp, 0, cp]])
    cy, sy = np.cos(yaw), np.sin(yaw)
    rot_y = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    world = local @ rot_p.T @ rot_y.T
    world += np.array([ra * cy, ra * sy, za])
    pts.append(world)
    dist.append(za + s)
    # Floor at half the centre thickness: leaf rims are not knife edges.
    thick.append(np.maximum(2 * half, cth))
  return np.concatenate(pts), np.concatenate(dist), np.concatenate(thick)


def _stack(rng, n):
  num = int(rng.integers(2, 5))
  counts = np.full(num, n // num)
  counts[: n - counts.sum()] += 1
  pts, thick = [], []
  z0 = 0.0
  for c in counts:
    shape = rng.choice(['box', 'sphere', 'cylinder'])
    if shape == 'box':
      e = rng.uniform([0.2, 0.2, 0.1], [0.8, 0.8, 0.6])
      p = rng.uniform(-e / 2, e / 2, (c, 3))
      p[:, 2] += z0 + e[2] / 2
      t = np.full(c, e.min())
      z0 += e[2]
    elif shape == 'sphere':
      radius = rng.uniform(0.15, 0.4)
      v = rng.normal(size=(c, 3))
      v /= np.linalg.norm(v, axis=-1, keepdims=True)
      p = v * radius * rng.uniform(0, 1, (c, 1)) ** (1 / 3)
      p[:, 2] += z0 + radius
      t = np.full(c, 2 * radius)
      z0 += 2 * radius
    else:
      radius = rng.uniform(0.1, 0.4)
      hgt = rng.uniform(0.1, 0.6)
      ang = rng.uniform(0, 2 * np.pi, c)
      rad = radius * np.sqrt(rng.uniform(0, 1, c))
      p = np.stack([rad * np.cos(ang), rad * np.sin(ang),
                    z0 + rng.uniform(0, hgt, c)], -1)
      t = np.full(c, min(2 * radius, hgt))
      z0 += hgt
    pts.append(p)
    thick.append(t)
  p = np.concatenate(pts)
  return p, p[:, 2].copy(), np.concatenate(thick)


def _blob(rng, n):
  num = int(rng.integers(3, 7))
  centres = rng.normal(scale=0.35, size=(num, 3))
  radii = rng.uniform(0.15, 0.5, num)
  vol = radii ** 3
  owner = rng.choice(num, size=n, p=vol / vol.sum())
  v = rng.normal(size=(n, 3))
  v /= np.linalg.norm(v, axis=-1, keepdims=True)
  p = centres[owner] + v * (radii[owner] * rng.uniform(0, 1, n) ** (1 / 3))[
    :, None]
  p[:, 2] -= p[:, 2].min()
  return p, p[:, 2].copy(), 2 * radii[owner]


_GENERATORS = {'beam': _beam, 'plant': _plant, 'stack': _stack,
               'blob': _blob}


def ground_truth_field(dist, thickness, E, model):
  """The documented rule (module docstring) for valid points.

  Args:
    dist: (n,) distance to the support [m], >= 0.
    thickness: (n,) local thickness [m], > 0.
    E: mean Young's modulus [Pa].
    model: constitutive-model name.

  Returns:
    (n, 3) float64 multipliers (E, nu, rho) with mean exactly 1 (to
    rounding).
  """
  if model == 'rigid' or model in FLUIDS:
    return np.ones((len(dist), 3))
  s = float(np.clip(1.0 + 0.3 * (6.0 - np.log10(E)), 0.4, 1.6))
  d_n = dist / max(float(dist.max()), 1e-9)
  lt = np.log(thickness)
  t_n = np.clip(lt - lt.mean(), -T_CLIP, T_CLIP)
  logs = np.stack([
    s * (A_D * (0.5 - d_n) + A_T * t_n),
    s * (-B_D * (0.5 - d_n)),
    s * C_T * t_n,
  ], -1)
  w = np.exp(logs - logs.max(0))
  return w / w.mean(0)


def make_object(seed: int, num_points: int = 256, kind: str | None = None,
                min_fill: float = 0.75) -> SyntheticObject:
  """One deterministic synthetic object.

  Args:
    seed: integer seed; equal seeds give identical objects.
    num_points: N, the padded size.
    kind: object family (KINDS) or None for a seeded random choice.
    min_fill: the number of valid points is uniform in
      [min_fill * N, N]; 1.0 means no padding.

  Returns:
    A :class:`SyntheticObject`.
  """
  if kind is not None and kind not in KINDS:
    raise MPDPError(f'Unknown synthetic object kind {kind!r}; use {KINDS}.')
  if not 0.0 < min_fill <= 1.0 or num_points < 8:
    raise MPDPError(
      f'make_object: need num_points >= 8 and 0 < min_fill <= 1, got '
      f'{num_points}, {min_fill}.')
  rng = np.random.default_rng(seed)
  if kind is None:
    kind = KINDS[int(rng.integers(len(KINDS)))]
  n_valid = int(rng.integers(int(np.ceil(min_fill * num_points)),
                             num_points + 1))
  pts, dist, thick = _GENERATORS[kind](rng, n_valid)
  yaw = rng.uniform(0, 2 * np.pi)
  cy, sy = np.cos(yaw), np.sin(yaw)
  rot = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
  scale = rng.uniform(0.5, 2.0)
  pts = (pts @ rot.T) * scale + rng.uniform(-1, 1, 3)
  dist, thick = dist * scale, thick * scale
  perm = rng.permutation(n_valid)
  pts, dist, thick = pts[perm], dist[perm], thick[perm]
  model = str(rng.choice(_MODELS, p=_MODEL_P / _MODEL_P.sum()))
  E = float(10 ** rng.uniform(4.0, 8.0))
  nu = float(rng.uniform(0.2, 0.45))
  rho = float(10 ** rng.uniform(np.log10(300), np.log10(3000)))
  field = ground_truth_field(dist, thick, E, model)

  def pad(a):
    out = np.zeros((num_points,) + a.shape[1:], np.float32)
    out[:n_valid] = a
    return out

  mask = np.arange(num_points) < n_valid
  return SyntheticObject(
    points=pad(pts), mask=mask, field=pad(field), E=E, nu=nu, rho=rho,
    model=model, kind=kind, dist=pad(dist), thickness=pad(thick))


def make_beam(seed: int, num_points: int = 256, E: float = 1e6,
              nu: float = 0.3, rho: float = 1000.0,
              model: str = 'neo_hookean') -> SyntheticObject:
  """An axis-aligned cantilever (root at x = 0, z up), no padding.

  For simulation experiments: unlike :func:`make_object` there is no random
  pose and the mean properties are given.

  Returns:
    A :class:`SyntheticObject` with ``kind='beam'``; points in metres with the
    root face at x = 0 and the beam centred on y = 0.
  """
  rng = np.random.default_rng(seed)
  pts, dist, thick = _beam(rng, num_points)
  pts[:, 2] -= pts[:, 2].mean()
  field = ground_truth_field(dist, thick, E, model)
  return SyntheticObject(
    points=pts.astype(np.float32), mask=np.ones(num_points, bool),
    field=field.astype(np.float32), E=float(E), nu=float(nu),
    rho=float(rho), model=model, kind='beam',
    dist=dist.astype(np.float32), thickness=thick.astype(np.float32))


def make_dataset(seed: int, num_objects: int, num_points: int = 256,
                 min_fill: float = 0.75) -> dict[str, np.ndarray]:
  """A stacked batch of objects: seeds ``seed * 100003 + i``.

  Returns:
    dict with 'points' (B, N, 3), 'mask' (B, N), 'field' (B, N, 3),
    'means' (B, MEANS_DIM) float32 arrays and 'kind' (B,) strings.
  """
  objs = [make_object(seed * 100003 + i, num_points, min_fill=min_fill)
          for i in range(num_objects)]
  return {
    'points': np.stack([o.points for o in objs]),
    'mask': np.stack([o.mask for o in objs]),
    'field': np.stack([o.field for o in objs]),
    'means': np.stack([np.asarray(o.means) for o in objs]),
    'kind': np.array([o.kind for o in objs]),
  }


def field_at(obj: SyntheticObject, query: np.ndarray) -> np.ndarray:
  """The ground-truth rule evaluated at arbitrary points of an object.

  Each query point (e.g. a driving particle that the pipeline sampled
  inside the object) takes the distance-to-support ``d`` and thickness
  ``t`` of the nearest valid point of ``obj``; the documented rule
  (:func:`ground_truth_field`) is then applied over the query set, so the
  result has mean exactly 1 over the queries. The rule is scale-free
  (``d / max d`` and ``t / geomean t``), so ``obj`` may be rescaled as
  long as the queries are in the same frame as ``obj.points``.

  Args:
    obj: the object (points, dist, thickness, E, model).
    query: (M, 3) points in the frame of ``obj.points``.

  Returns:
    (M, 3) float64 multipliers of (E, nu, rho), mean 1 over the queries.
  """
  import scipy.spatial

  query = np.asarray(query, np.float64)
  if query.ndim != 2 or query.shape[1] != 3 or len(query) == 0:
    raise MPDPError(f'field_at: query must be (M, 3) with M >= 1, got '
                    f'{query.shape}.')
  valid = np.asarray(obj.mask)
  tree = scipy.spatial.cKDTree(np.asarray(obj.points, np.float64)[valid])
  _, nn = tree.query(query)
  dist = np.asarray(obj.dist, np.float64)[valid][nn]
  thick = np.asarray(obj.thickness, np.float64)[valid][nn]
  return ground_truth_field(dist, thick, obj.E, obj.model)


def transform_object(obj: SyntheticObject, scale: float,
                     offset=(0.0, 0.0, 0.0)) -> SyntheticObject:
  """``obj`` with points mapped to ``scale * p + offset`` (valid rows);
  distances and thicknesses scale too, so the field is unchanged."""
  pts = np.where(obj.mask[:, None],
                 obj.points * scale + np.asarray(offset, np.float32), 0.0)
  return dataclasses.replace(
    obj, points=pts.astype(np.float32),
    dist=(obj.dist * scale).astype(np.float32),
    thickness=(obj.thickness * scale).astype(np.float32))
