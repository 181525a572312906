"""PhysGaussian's object as a segmentation (opacity threshold + sim_area)."""

from __future__ import annotations

import numpy as np

from physsplat_jax.physgaussian.transform import select_particles
from physsplat_jax.segmentation.base import Segmentation
from physsplat_jax.types import Gaussians


def segment_from_physgaussian(gaussians: Gaussians, config,
                              name: str = 'object') -> Segmentation:
  """The one object PhysGaussian simulates: opacity threshold + sim_area.

  Args:
    gaussians: the scene's Gaussians (input coordinates).
    config: a :class:`~physsplat_jax.physgaussian.PhysGaussianConfig`.
    name: the object's name.

  Returns:
    A :class:`Segmentation` with one object (the rest is background).
  """
  rows = select_particles(config, np.asarray(gaussians.means),
                          np.asarray(gaussians.opacities))
  ids = np.full(gaussians.num, -1, np.int32)
  ids[rows] = 0
  return Segmentation(ids, (name,), method='boxes')
