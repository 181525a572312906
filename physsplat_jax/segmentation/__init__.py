"""Segmentation: per-Gaussian object ids from PLY attributes, boxes,
geometry (support plane + clusters) or 2D masks; hole filling under moved
objects. Host-side NumPy/SciPy (data-dependent sizes, not differentiated).
See docs/segmentation.md.
"""

from physsplat_jax.segmentation.attributes import (
  segment_by_attribute as segment_by_attribute,
)
from physsplat_jax.segmentation.auto import METHODS as METHODS
from physsplat_jax.segmentation.auto import segment as segment
from physsplat_jax.segmentation.base import BACKGROUND as BACKGROUND
from physsplat_jax.segmentation.base import Segmentation as Segmentation
from physsplat_jax.segmentation.base import (
  SegmentationError as SegmentationError,
)
from physsplat_jax.segmentation.boxes import (
  segment_by_boxes as segment_by_boxes,
)
from physsplat_jax.segmentation.geometric import (
  cluster_points as cluster_points,
)
from physsplat_jax.segmentation.geometric import (
  fit_plane_ransac as fit_plane_ransac,
)
from physsplat_jax.segmentation.geometric import (
  segment_geometric as segment_geometric,
)
from physsplat_jax.segmentation.holes import (
  fill_support_hole as fill_support_hole,
)
from physsplat_jax.segmentation.masks import (
  contribution_weights as contribution_weights,
)
from physsplat_jax.segmentation.masks import lift_masks as lift_masks
from physsplat_jax.segmentation.masks import (
  unoccluded_weights as unoccluded_weights,
)
