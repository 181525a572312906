"""Controls for a user's own capture: what is simulated, and the camera path.

Real 3DGS captures hold far more than the object to simulate: floaters
(stray Gaussians far from any surface, which stretch the grid), faint
Gaussians, and a background. :func:`filter_scene` takes the movable
Gaussians that the user excluded or that look like floaters out of the
simulation: their object id becomes -1 (background), so they stay in the
render, static, and do not size the grid. Three :class:`PrepareConfig`
fields control it, each overridable:

- ``roi``: an axis-aligned box in scene units and axes (PhysGaussian's
  ``sim_area`` order, tested with
  :func:`physsplat_jax.segmentation.boxes.inside_box`);
- ``min_opacity``: the activated opacity below which a Gaussian stays
  static (PhysGaussian's ``opacity_threshold``);
- ``floater_factor``: a Gaussian whose :data:`FLOATER_K`-th nearest
  neighbour within its object lies farther than ``floater_factor`` times the
  object's median such distance is a floater (a density test: the bulk of a
  surface is dense, floaters are isolated); 0 disables it.

:func:`camera_orbit` gives the orbit of ``camera_path='orbit'``; the
per-frame camera is :func:`frame_camera` (traced arrays, so a moving
camera never recompiles the renderer).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from absl import logging
import scipy

from physsplat_jax import cameras as cam_lib
from physsplat_jax import struct
from physsplat_jax.pipeline.config import CameraPath
from physsplat_jax.pipeline.config import PipelineError
from physsplat_jax.pipeline.config import PrepareConfig
from physsplat_jax.segmentation import boxes
from physsplat_jax.types import Array
from physsplat_jax.types import Camera
from physsplat_jax.types import Scene
from physsplat_jax.types import device_array

FLOATER_K = 8


def floater_mask(points, factor: float, k: int = FLOATER_K) -> np.ndarray:
  """(N,) bool: points whose k-th nearest neighbour is farther than
  ``factor`` times the median k-th-neighbour distance (none for fewer than
  ``2 k`` points or ``factor`` 0)."""
  x = np.asarray(points, np.float64)
  if factor <= 0 or len(x) < 2 * k:
    return np.zeros(len(x), bool)
  d, _ = scipy.spatial.cKDTree(x).query(x, k=k + 1, workers=-1)
  dk = d[:, k]
  med = float(np.median(dk))
  if not med > 0:  # over half the points coincide: no scale to compare
    return np.zeros(len(x), bool)
  return dk > factor * med


def _extent(x: np.ndarray) -> float:
  return float(np.max(np.ptp(x, axis=0))) if len(x) else 0.0


def filter_scene(scene: Scene, cfg: PrepareConfig) -> tuple[Scene, dict]:
  """The scene with excluded movable Gaussians moved to the background.

  Args:
    scene: the segmented scene.
    cfg: ``roi``, ``min_opacity`` and ``floater_factor`` are read.

  Returns:
    (scene with ``object_ids`` -1 for the excluded Gaussians, report dict:
    the counts per reason and the largest side of the movable Gaussians'
    box [m] before and after removing floaters).

  Raises:
    PipelineError: the ROI or opacity filter leaves a movable object with
      no Gaussian.
  """
  ids = np.asarray(scene.object_ids).copy()
  fixed = np.array([o.fixed for o in scene.objects] + [True])
  movable = (ids >= 0) & ~fixed[ids]  # id -1 indexes the trailing True
  means = np.asarray(scene.gaussians.means, np.float64)
  s = float(scene.meters_per_unit)
  drop = np.zeros(len(ids), bool)
  report = dict(outside_roi=0, below_min_opacity=0, floaters=0)
  if cfg.roi is not None:
    out = movable & ~boxes.inside_box(means, cfg.roi)
    report['outside_roi'] = int(out.sum())
    drop |= out
  if cfg.min_opacity > 0:
    faint = movable & ~drop & (
      np.asarray(scene.gaussians.opacities) < cfg.min_opacity)
    report['below_min_opacity'] = int(faint.sum())
    drop |= faint
  for o in np.unique(ids[movable]):
    if not np.any((ids == o) & ~drop):
      raise PipelineError(
        f'object {scene.objects[o].name!r}: none of its '
        f'{int(np.sum(ids == o))} Gaussians is left to simulate after '
        f'roi={cfg.roi} and min_opacity={cfg.min_opacity}; widen roi, lower '
        'min_opacity, or mark the object fixed.')
  kept = movable & ~drop
  before = _extent(means[kept]) * s
  if cfg.floater_factor > 0:
    for o in np.unique(ids[kept]):
      rows = np.nonzero(kept & (ids == o))[0]
      fl = rows[floater_mask(means[rows], cfg.floater_factor)]
      drop[fl] = True
      report['floaters'] += int(len(fl))
  after = _extent(means[movable & ~drop]) * s
  report.update(extent_before_floaters_m=before, extent_m=after)
  if report['floaters']:
    logging.info(
      '%s: %d floaters (8th neighbour > %g x the median distance) stay '
      'static; the simulated extent shrinks from %.3g m to %.3g m (set '
      'floater_factor=0 to keep them)', scene.name, report['floaters'],
      cfg.floater_factor, before, after)
  if report['outside_roi'] or report['below_min_opacity']:
    logging.info('%s: %d Gaussians outside roi and %d below min_opacity '
                 'stay static', scene.name, report['outside_roi'],
                 report['below_min_opacity'])
  if not drop.any():
    return scene, report
  ids[drop] = -1
  return scene.replace(object_ids=jnp.asarray(ids, jnp.int32)), report


class CameraOrbit(struct.PyTreeNode):
  """A camera turning about an axis (arrays: changing it never recompiles).

  Attributes:
    center: (3,) a point of the axis [scene units].
    axis: (3,) unit axis (the scene's up).
    degrees: () total turn over the video (0: a fixed camera).
  """

  center: Array
  axis: Array
  degrees: Array


def camera_orbit(scene: Scene, rows: np.ndarray, cfg: PrepareConfig
                 ) -> CameraOrbit:
  """The orbit of ``cfg.camera_path`` about the scene's up axis through the
  centre of the box of the simulated Gaussians (``rows``)."""
  m = np.asarray(scene.gaussians.means, np.float64)[rows]
  center = 0.5 * (m.min(0) + m.max(0))
  deg = cfg.orbit_degrees if cfg.camera_path is CameraPath.ORBIT else 0.0
  return CameraOrbit(center=device_array(center, jnp.float32),
                     axis=device_array(scene.up_vector, jnp.float32),
                     degrees=device_array(deg, jnp.float32))


def frame_camera(camera: Camera, orbit: CameraOrbit, frame, num_frames
                 ) -> Camera:
  """``camera`` turned by ``orbit.degrees * frame / num_frames`` (``frame``
  and ``num_frames`` may be traced: a video of another length reuses the
  compiled camera)."""
  angle = orbit.degrees * jnp.asarray(frame, jnp.float32) / jnp.maximum(
    jnp.asarray(num_frames, jnp.float32), 1.0)
  vm = cam_lib.orbit_viewmat(camera.viewmat, orbit.center, orbit.axis, angle)
  return camera.replace(viewmat=vm.astype(camera.viewmat.dtype))
