"""Fixed objects as boundary conditions: a support plane and anchor boxes."""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from physsplat_jax.pipeline.config import PipelineError


@dataclasses.dataclass(frozen=True)
class Colliders:
  """Fixed objects turned into boundary conditions (simulation frame).

  Attributes:
    ground_z: height of the support plane [m], or None.
    anchors: ((lo (3,), hi (3,)), ...) sticky boxes [m]: fixed objects that
      are not a plane under the movable ones (e.g. the pot of a plant).
    notes: one line per fixed object saying what it became (for reports;
      not part of equality, so it never causes a recompilation).
  """

  ground_z: float | None
  anchors: tuple[tuple[tuple[float, ...], tuple[float, ...]], ...]
  notes: tuple[str, ...] = dataclasses.field(default=(), compare=False)


def find_colliders(means_sim: np.ndarray, object_ids: np.ndarray,
                   movable: Sequence[int], fixed: Sequence[int],
                   names: Sequence[str], tol: float) -> Colliders:
  """Classifies fixed objects into a support plane and anchor boxes.

  A fixed object whose top (99th height percentile of its Gaussians under
  the movable objects' footprint) lies at or below the lowest movable point
  (+ ``tol``) is a support: the highest such top becomes the ground plane.
  Any other fixed object that reaches into the movable objects' footprint is
  an anchor box (its bounding box; grid velocity zero inside, as
  PhysGaussian's fixed ``cuboid``). Without a support the ground is the
  lowest movable point.
  """
  mov = np.isin(object_ids, np.asarray(movable, np.int64))
  if not mov.any():
    raise PipelineError('the scene has no movable object to simulate; mark '
                        'at least one object as not fixed.')
  lo = means_sim[mov].min(0)
  hi = means_sim[mov].max(0)
  pad = 0.1 * float(np.max(hi[:2] - lo[:2])) + tol
  ground = None
  anchors = []
  notes = []
  for o in fixed:
    pts = means_sim[object_ids == o]
    if len(pts) == 0:
      continue
    under = np.all((pts[:, :2] >= lo[:2] - pad) & (pts[:, :2] <= hi[:2] + pad),
                   axis=1)
    if not under.any():
      notes.append(f'{names[o]}: fixed, away from the movable objects '
                   '(static, not simulated)')
      continue
    top = float(np.percentile(pts[under, 2], 99.0))
    if top <= lo[2] + tol:
      if ground is None or top > ground:
        ground = top
      notes.append(f'{names[o]}: fixed support, ground plane at z={top:.4f} m')
    else:
      blo = pts[under].min(0)
      bhi = pts[under].max(0)
      anchors.append((tuple(float(v) for v in blo),
                      tuple(float(v) for v in bhi)))
      notes.append(f'{names[o]}: fixed anchor box {np.round(blo, 4)} .. '
                   f'{np.round(bhi, 4)} m (sticky)')
  if ground is None:
    ground = float(lo[2])
    notes.append(f'no fixed support under the movable objects: ground plane '
                 f'at their lowest point z={ground:.4f} m')
  return Colliders(ground_z=ground, anchors=tuple(anchors), notes=tuple(notes))
