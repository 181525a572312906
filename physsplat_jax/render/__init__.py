"""Pure-JAX Gaussian-splat rendering (gsplat semantics), CPU and GPU.

See :mod:`physsplat_jax.render.raster` for the algorithm and docs/rendering.md
for the semantics, the gsplat/INRIA differences and benchmarks.
"""

from physsplat_jax.render.project import Projected as Projected
from physsplat_jax.render.project import project as project
from physsplat_jax.render.raster import RenderConfig as RenderConfig
from physsplat_jax.render.raster import RenderOutput as RenderOutput
from physsplat_jax.render.raster import fit_render_config as fit_render_config
from physsplat_jax.render.raster import gaussian_colors as gaussian_colors
from physsplat_jax.render.raster import render as render
from physsplat_jax.render.raster import (
  render_differentiable as render_differentiable,
)
from physsplat_jax.render.raster import render_image as render_image
