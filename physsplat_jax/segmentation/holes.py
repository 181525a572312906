"""Filling the hole an object leaves in its support.

A 3DGS capture never sees the table under a cup, so when the cup moves the
table shows a hole. :func:`fill_support_hole` extends the support into the
object's footprint by copying nearby support Gaussians:

1. **Support**: by default the label (another object, or the background)
   with the most Gaussians in a ring around the object's footprint and not
   above the object's base.
2. **Local plane**: least squares (SVD) through the support Gaussians of
   that ring, normal oriented along the scene's up.
3. **Hole**: the object's centres projected onto the plane, rasterised on a
   2D grid whose cell is the ring's typical Gaussian spacing (median
   nearest-neighbour distance in the plane), dilated by ``dilate`` cells;
   cells already covered by a support Gaussian on the plane are not holes.
4. **Copies**: one Gaussian per hole cell, placed at the cell centre
   (jittered by up to a quarter cell) on the plane, shifted by the ring's
   median height residual; every other attribute (scales, rotation,
   opacity, SH, normals, extras) is copied from a donor picked at random
   among the ``num_donors`` ring Gaussians nearest to the cell, so colour
   and scale statistics follow the surroundings (including gradients).

The new Gaussians are appended to the support object; the removed object
itself stays in the scene (the caller moves or deletes it), so while it is
in place the copies are hidden underneath it.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import scipy

from physsplat_jax.segmentation.base import SegmentationError
from physsplat_jax.types import Scene
from physsplat_jax.types import concatenate_gaussians
from physsplat_jax.values import is_int
from physsplat_jax.values import is_real


def _plane_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  a = np.eye(3)[np.argmin(np.abs(n))]
  e1 = np.cross(n, a)
  e1 /= np.linalg.norm(e1)
  return e1, np.cross(n, e1)


def _check_fill_args(scene, object_index, support_index, ring_width, dilate,
                     num_donors, max_new) -> None:
  """Refuses arguments that would fail deep inside NumPy or be misread."""
  n = scene.num_objects
  if not is_int(object_index) or not 0 <= object_index < n:
    raise SegmentationError(
      f'object_index={object_index!r}: must be an object of the scene, an '
      f'integer in [0, {n}) ({n} objects)')
  if support_index is not None:
    if not is_int(support_index) or not -1 <= support_index < n:
      raise SegmentationError(
        f'support_index={support_index!r}: must be another object, an '
        f'integer in [0, {n}), or -1 for the background; or None to pick '
        'the support automatically')
    if support_index == object_index:
      raise SegmentationError(
        f'support_index={support_index} is the object itself; pass the '
        'object it rests on (or -1 for the background, None to pick it)')
  if ring_width is not None and not (is_real(ring_width) and ring_width > 0):
    raise SegmentationError(
      f'ring_width={ring_width!r}: must be a positive length in scene '
      'units, or None for 30 % of the footprint\'s size')
  for name, value, low in (('dilate', dilate, 0), ('num_donors', num_donors, 1),
                           ('max_new', max_new, 1)):
    if not is_int(value) or value < low:
      raise SegmentationError(
        f'{name}={value!r}: must be an integer >= {low}')


def fill_support_hole(
  scene: Scene,
  object_index: int,
  support_index: int | None = None,
  ring_width: float | None = None,
  dilate: int = 1,
  num_donors: int = 4,
  seed: int = 0,
  max_new: int = 200_000,
) -> Scene:
  """Adds support Gaussians under an object's footprint (module docstring).

  Args:
    scene: the scene.
    object_index: the object that will move away.
    support_index: the object (or -1 for the background) to extend; None
      picks it automatically.
    ring_width: width of the ring around the footprint used for the plane
      and the donors [scene units]; default 30 % of the footprint's size.
    dilate: grid cells added around the footprint.
    num_donors: donors drawn from this many nearest ring Gaussians.
    seed: NumPy seed (jitter and donors).
    max_new: cap on added Gaussians (error beyond it: the cell is tiny).

  Returns:
    A new :class:`Scene` with the copies appended (``object_ids`` set to
    the support's id). If nothing needs filling the scene is returned as is.

  Raises:
    SegmentationError (a ValueError): an argument out of range (unknown
      object or support, the support being the object, ``ring_width`` not
      positive, ``dilate`` < 0, ``num_donors`` or ``max_new`` < 1), no
      support Gaussians around the footprint, or too many Gaussians to add.
  """
  _check_fill_args(scene, object_index, support_index, ring_width, dilate,
                   num_donors, max_new)
  g = scene.gaussians
  ids = np.asarray(scene.object_ids)
  x = np.asarray(g.means, np.float64)
  up = scene.up_vector
  obj = ids == object_index
  if not obj.any():
    raise SegmentationError(f'object {object_index} '
                            f'({scene.objects[object_index].name!r}) has no '
                            'Gaussians')
  e1, e2 = _plane_basis(up)
  xo = x[obj]
  uv_o = np.stack([xo @ e1, xo @ e2], 1)
  size = float(np.linalg.norm(uv_o.max(0) - uv_o.min(0))) or 1e-6
  ring_width = 0.3 * size if ring_width is None else float(ring_width)
  base_h = float(np.percentile(xo @ up, 2.0))
  # Ring: non-object Gaussians whose projection is near the footprint.
  tree_o = scipy.spatial.cKDTree(uv_o)
  uv_all = np.stack([x @ e1, x @ e2], 1)
  d_fp, _ = tree_o.query(uv_all, distance_upper_bound=ring_width)
  near = np.isfinite(d_fp) & ~obj
  low = (x @ up) <= base_h + 0.5 * ring_width
  cand = near & low
  if support_index is None:
    labels, counts = np.unique(ids[cand], return_counts=True)
    labels, counts = labels[labels != object_index], counts[
      labels != object_index]
    if labels.size == 0:
      raise SegmentationError(
        f'no Gaussians around the footprint of object {object_index} '
        f'({scene.objects[object_index].name!r}) within ring_width='
        f'{ring_width:.3g}; pass support_index and a larger ring_width')
    support_index = int(labels[np.argmax(counts)])
  ring = cand & (ids == support_index)
  if ring.sum() < 3:
    raise SegmentationError(
      f'only {int(ring.sum())} Gaussians of support {support_index} around '
      f'object {object_index}; pass a larger ring_width')
  xr = x[ring]
  c = xr.mean(0)
  _, _, vt = np.linalg.svd(xr - c, full_matrices=False)
  n = vt[-1] if vt[-1] @ up >= 0 else -vt[-1]
  if abs(n @ up) < 0.5:
    n = up  # a steep fit means a bad ring; the support is horizontal
  e1, e2 = _plane_basis(n)
  to_uv = lambda p: np.stack([(p - c) @ e1, (p - c) @ e2], 1)
  uv_r = to_uv(xr)
  h_r = (xr - c) @ n
  tree_r = scipy.spatial.cKDTree(uv_r)
  dnn, _ = tree_r.query(uv_r, k=2)
  cell = float(np.median(dnn[:, 1]))
  if not cell > 0:
    raise SegmentationError(
      'support Gaussians around the object coincide; cannot '
      'estimate their spacing')
  uv_o = to_uv(xo)
  lo = uv_o.min(0) - (dilate + 1) * cell
  hi = uv_o.max(0) + (dilate + 1) * cell
  shape = np.ceil((hi - lo) / cell).astype(int) + 1
  if np.prod(shape) > 4 * max_new:
    raise SegmentationError(
      f'hole grid {shape} too fine (cell {cell:.3g}); the '
      'support spacing is tiny compared to the object')
  foot = np.zeros(shape, bool)
  ij = np.floor((uv_o - lo) / cell).astype(int)
  foot[ij[:, 0], ij[:, 1]] = True
  if dilate > 0:
    foot = scipy.ndimage.binary_dilation(foot, iterations=dilate)
  # Cells already covered by support Gaussians lying on the plane.
  sup = ids == support_index
  xs = x[sup]
  on_plane = np.abs((xs - c) @ n) <= max(3 * cell, 0.1 * ring_width)
  uv_s = to_uv(xs[on_plane])
  ij_s = np.floor((uv_s - lo) / cell).astype(int)
  inside = np.all((ij_s >= 0) & (ij_s < shape), axis=1)
  covered = np.zeros(shape, bool)
  covered[ij_s[inside, 0], ij_s[inside, 1]] = True
  hole = foot & ~covered
  cells = np.argwhere(hole)
  if cells.shape[0] == 0:
    return scene
  if cells.shape[0] > max_new:
    raise SegmentationError(
      f'{cells.shape[0]} Gaussians to add exceeds max_new='
      f'{max_new}')
  rng = np.random.default_rng(seed)
  uv_new = lo + (cells + 0.5 + rng.uniform(-0.25, 0.25, cells.shape)) * cell
  k = min(num_donors, uv_r.shape[0])
  _, nn = tree_r.query(uv_new, k=k)
  nn = nn.reshape(uv_new.shape[0], k)
  pick = nn[np.arange(uv_new.shape[0]), rng.integers(0, k, uv_new.shape[0])]
  donors = np.nonzero(ring)[0][pick]
  h = float(np.median(h_r))
  pos = c + uv_new[:, :1] * e1 + uv_new[:, 1:] * e2 + h * n
  new = g.subset(donors)
  new = new.replace(means=jnp.asarray(pos, g.means.dtype))
  out_g = concatenate_gaussians([g, new])
  new_ids = np.concatenate([ids, np.full(donors.size, support_index,
                                         ids.dtype)])
  return scene.replace(gaussians=out_g,
                       object_ids=jnp.asarray(new_ids, jnp.int32))
