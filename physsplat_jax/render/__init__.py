"""Pure-JAX Gaussian-splat rendering (gsplat semantics), CPU and GPU.

See :mod:`physsplat_jax.render.raster` for the algorithm and docs/rendering.md
for the semantics, the gsplat/INRIA differences and benchmarks; on GPUs the
compositing runs as Pallas (Triton) kernels (:mod:`.pallas_raster`).
"""

import sys as _sys
import types as _types
import warnings as _warnings

from physsplat_jax.render.project import Projected as Projected
from physsplat_jax.render.project import project as project
from physsplat_jax.render.config import (
  RenderCapacityError as RenderCapacityError,
)
from physsplat_jax.render.config import (
  RenderConfigError as RenderConfigError,
)
from physsplat_jax.render.config import (
  RenderInputError as RenderInputError,
)
from physsplat_jax.render.images import PendingRender as PendingRender
from physsplat_jax.render.raster import RenderConfig as RenderConfig
from physsplat_jax.render.raster import RenderOutput as RenderOutput
from physsplat_jax.render.images import (
  count_intersections as count_intersections,
)
from physsplat_jax.render.images import fit_render_config as fit_render_config
from physsplat_jax.render.raster import gaussian_colors as gaussian_colors
from physsplat_jax.render.raster import render as render
from physsplat_jax.render.raster import (
  render_differentiable as render_differentiable,
)
from physsplat_jax.render.images import render_image as render_image
from physsplat_jax.render.images import (
  render_image_async as render_image_async,
)
from physsplat_jax.sh_rotation import rotate_sh as rotate_sh
from physsplat_jax.render.slices import draw_line as draw_line
from physsplat_jax.render.slices import space_time_slice as space_time_slice
from physsplat_jax.render.views import render_scene as render_scene
from physsplat_jax.render.views import resize_camera as resize_camera
from physsplat_jax.render.views import scene_camera as scene_camera


class _CallableModule(_types.ModuleType):
  """``physsplat_jax.render`` is this subpackage; calling it as a function
  (its old top-level meaning) still renders, with a deprecation warning."""

  def __call__(self, *args, **kwargs):
    _warnings.warn(
      'calling physsplat_jax.render(...) is deprecated: use '
      'physsplat_jax.render.render(...) or physsplat_jax.render_image(...); '
      'physsplat_jax.render is the rendering subpackage.',
      DeprecationWarning, stacklevel=2)
    return render(*args, **kwargs)


_sys.modules[__name__].__class__ = _CallableModule
