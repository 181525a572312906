"""Rendering a whole scene from one of its cameras (host-side convenience).

:func:`render_scene` picks a camera (one of the scene's, a given
:class:`~physsplat_jax.types.Camera`, or one fitted to the scene), brings it to
the requested size, renders with :func:`~physsplat_jax.render.images.
render_image` (never dropping Gaussians) and returns the image as NumPy. It
is what ``python -m experiments.render`` calls. Inside ``jit`` (simulation,
training) call :func:`~physsplat_jax.render.raster.render` directly.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from physsplat_jax import cameras as cam_lib
from physsplat_jax.render import images
from physsplat_jax.render import raster
from physsplat_jax.render.config import RenderInputError
from physsplat_jax.types import Camera
from physsplat_jax.types import Gaussians
from physsplat_jax.types import Scene
from physsplat_jax.types import up_vector

DEFAULT_WIDTH, DEFAULT_HEIGHT = 512, 384
BACKGROUNDS = {
  'black': (0.0, 0.0, 0.0),
  'white': (1.0, 1.0, 1.0),
  'grey': (0.5, 0.5, 0.5),
  'gray': (0.5, 0.5, 0.5),
}


def parse_background(value) -> tuple[float, float, float]:
  """'white', 'black', 'grey', '0.1,0.2,0.3' or a 3-sequence -> RGB tuple.

  Raises:
    RenderInputError: not a name nor three numbers in [0, 1] (NaN fails
      the range check too).
  """
  if isinstance(value, str):
    key = value.strip().lower()
    if key in BACKGROUNDS:
      return BACKGROUNDS[key]
    parts = [p for p in key.replace(' ', ',').split(',') if p]
  else:
    parts = list(np.asarray(value, np.float64).reshape(-1))
  try:
    rgb = tuple(float(p) for p in parts)
  except ValueError:
    rgb = ()
  if len(rgb) != 3 or not all(0.0 <= c <= 1.0 for c in rgb):
    raise RenderInputError(
      f'background {value!r}: use a name ({", ".join(BACKGROUNDS)}) or three '
      'numbers in [0, 1] such as "1,1,1"'
    )
  return rgb


def resize_camera(camera: Camera, width: int, height: int) -> Camera:
  """The camera at ``width x height`` with square pixels kept.

  Same aspect ratio: intrinsics scaled. Otherwise the focal length follows
  the height (the vertical field of view is kept), the principal point is
  scaled vertically and re-centred horizontally.
  """
  width, height = int(width), int(height)
  if width < 1 or height < 1:
    raise RenderInputError(f'image size must be positive, got {width}x{height}')
  if (width, height) == (camera.width, camera.height):
    return camera
  if abs(camera.width / camera.height - width / height) < 1e-6:
    return camera.resized(width, height)
  s = height / camera.height
  return camera.replace(
    fx=camera.fx * s, fy=camera.fy * s,
    cx=jnp.asarray(width / 2.0, camera.fx.dtype), cy=camera.cy * s,
    width=width, height=height,
  )


def fit_scene_camera(
  gaussians: Gaussians, up=(0.0, 0.0, 1.0), width: int = DEFAULT_WIDTH,
  height: int = DEFAULT_HEIGHT, azimuth: float = -60.0,
  elevation: float = 25.0, fov_deg: float = 40.0, padding: float = 1.05,
) -> Camera:
  """A camera framing the 1st-99th percentile box of the centres.

  Percentiles keep a few floaters from shrinking the object
  (:func:`physsplat_jax.cameras.framing_box`, which also frames a single
  Gaussian); see :func:`physsplat_jax.cameras.fit_camera` for the angles.
  """
  lo, hi = cam_lib.framing_box(gaussians.means)
  return cam_lib.fit_camera(lo, hi, up=np.asarray(up, np.float64),
                            width=width, height=height, fov_deg=fov_deg,
                            azimuth=azimuth, elevation=elevation,
                            padding=padding)


def scene_camera(
  scene: Scene | Gaussians,
  camera: Camera | int | None = None,
  width: int | None = None,
  height: int | None = None,
) -> Camera:
  """The camera :func:`render_scene` uses.

  Args:
    scene: a :class:`Scene` or bare :class:`Gaussians`.
    camera: a Camera; an index into ``scene.cameras`` (-1: a fitted one);
      None: ``scene.cameras[0]`` if any, else fitted.
    width, height: output size (None: the camera's, or 512x384 when
      fitted; one given: the other follows the aspect ratio).

  Returns:
    A :class:`Camera`.

  Raises:
    ValueError: index out of range.
  """
  gauss = scene.gaussians if isinstance(scene, Scene) else scene
  cams = tuple(scene.cameras) if isinstance(scene, Scene) else ()
  if isinstance(camera, Camera):
    cam = camera
  elif camera is None and cams:
    cam = cams[0]
  elif camera is None or int(camera) == -1:
    up = scene.up_vector if isinstance(scene, Scene) else up_vector('z')
    w = width or (DEFAULT_WIDTH if height is None
                  else round(height * DEFAULT_WIDTH / DEFAULT_HEIGHT))
    h = height or round(w * DEFAULT_HEIGHT / DEFAULT_WIDTH)
    return fit_scene_camera(gauss, up=up, width=w, height=h)
  else:
    i = int(camera)
    if not 0 <= i < len(cams):
      raise RenderInputError(
        f'camera index {i}: the scene has {len(cams)} cameras; use '
        f'0..{len(cams) - 1}, or -1 for a camera fitted to the scene'
      )
    cam = cams[i]
  if width is None and height is None:
    return cam
  if width is None:
    width = round(height * cam.width / cam.height)
  if height is None:
    height = round(width * cam.height / cam.width)
  return resize_camera(cam, width, height)


def render_scene(
  scene: Scene | Gaussians,
  camera: Camera | int | None = None,
  width: int | None = None,
  height: int | None = None,
  background=(0.0, 0.0, 0.0),
  *,
  sh_degree: int | None = None,
  config: raster.RenderConfig = raster.RenderConfig(),
  return_output: bool = False,
):
  """Renders a scene to an image (host side; jitted inside).

  Args:
    scene: a :class:`Scene` (e.g. from ``physsplat_jax.io.scene.
      load_scene``) or bare :class:`Gaussians`.
    camera, width, height: see :func:`scene_camera`.
    background: RGB triple or a name ('black', 'white', 'grey').
    sh_degree: SH degree to evaluate (None: all the scene has; 0: flat
      colour).
    config: rasterizer settings (capacity grows by itself on overflow).
    return_output: return the full :class:`~physsplat_jax.render.raster.
      RenderOutput` (image, alpha, depth, counts) instead of the image.

  Returns:
    (H, W, 3) float32 NumPy image clipped to [0, 1], or the RenderOutput.
  """
  gauss = scene.gaussians if isinstance(scene, Scene) else scene
  if not isinstance(gauss, Gaussians):
    raise RenderInputError(
      f'render_scene: expected a Scene or Gaussians, got '
      f'{type(scene).__name__} (load one with physsplat_jax.io.scene.'
      'load_scene)'
    )
  cam = scene_camera(scene, camera, width, height)
  if sh_degree is not None:
    if not 0 <= int(sh_degree) <= 3:
      raise RenderInputError(f'sh_degree must be 0..3, got {sh_degree}')
    sh_degree = min(int(sh_degree), gauss.sh_degree)
    config = dataclasses.replace(config, sh_degree=sh_degree)
  out = images.render_image(gauss, cam, background=parse_background(
    background), config=config)
  if return_output:
    return out
  return np.clip(np.asarray(out.image, np.float32), 0.0, 1.0)
