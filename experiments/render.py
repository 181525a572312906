"""Renders a scene to a PNG.

  python -m experiments.render --scene=donut --out=/tmp/donut.png
  python -m experiments.render --scene=path/to/point_cloud.ply \\
      --camera_file=path/to/cameras.json --camera_index=3 --out=view.png

--scene is a built-in name (tabletop, ficus, donut) or a 3DGS
.ply/.splat/.spz file or output folder (physsplat_jax.load_scene). The
camera is one of the scene's (--camera_index; -1 fits one to the scene) or
one from --camera_file (INRIA cameras.json or transforms.json).
--rasterize_mode=antialiased renders as gsplat's antialiased mode, for
scenes trained with it (Mip-Splatting's 2D filter).
"""

import os
import time

import jax
from absl import flags
from absl import logging

from experiments.lib import cli
from physsplat_jax.io import cameras as camera_io
from physsplat_jax.io import video
from physsplat_jax.scenes import load_scene
from physsplat_jax.render import RenderConfig
from physsplat_jax.render import views
from physsplat_jax.render.config import RASTERIZE_MODES
from physsplat_jax.render.config import RenderInputError

_SCENE = flags.DEFINE_string('scene', None, 'Built-in name or 3DGS path.')
_OUT = flags.DEFINE_string('out', None, 'Output PNG.')
_CAMERA_FILE = flags.DEFINE_string('camera_file', None,
                                   'cameras.json or transforms.json.')
_CAMERA_INDEX = flags.DEFINE_integer(
  'camera_index', 0, "Camera index, of --camera_file's cameras if given; "
  '-1: fitted to the scene (with --camera_file: its first).')
_WIDTH = flags.DEFINE_integer('width', None, 'Width [px] (default: camera).')
_HEIGHT = flags.DEFINE_integer('height', None, 'Height [px].')
_BACKGROUND = flags.DEFINE_string('background', 'white',
                                  'white, black, grey or "r,g,b" in [0, 1].')
_SH_DEGREE = flags.DEFINE_integer('sh_degree', None, 'SH degree (0..3).')
_RASTERIZE_MODE = flags.DEFINE_enum(
  'rasterize_mode', 'classic', RASTERIZE_MODES,
  "RenderConfig.rasterize_mode: 'antialiased' for scenes trained with "
  "gsplat's antialiased mode (Mip-Splatting).")


def main(argv):
  del argv
  out = _OUT.value
  if os.path.isdir(out) or not out.lower().endswith('.png'):
    raise cli.usage_error(f'--out={out}: give the path of a .png file')
  cli.check_output_file('out', out)  # (else it failed after rendering)
  try:
    background = views.parse_background(_BACKGROUND.value)
  except RenderInputError:
    raise cli.usage_error(
      f'--background={_BACKGROUND.value}: give a name '
      f'({", ".join(views.BACKGROUNDS)}) or three numbers in [0, 1] such as '
      '"1,1,1"') from None
  for flag in (_WIDTH, _HEIGHT):  # (was 'image size must be positive')
    if flag.value is not None and flag.value < 1:
      raise cli.usage_error(f'--{flag.name}={flag.value}: give a whole '
                            'number of pixels >= 1, or leave it out for '
                            "the camera's")
  if _SH_DEGREE.value is not None and not 0 <= _SH_DEGREE.value <= 3:
    raise cli.usage_error(f'--sh_degree={_SH_DEGREE.value}: give 0..3, or '
                          "leave it out for all the scene's")
  logging.info('devices %s', jax.devices())
  scene = load_scene(_SCENE.value)
  camera = _CAMERA_INDEX.value
  if _CAMERA_FILE.value:
    cams = camera_io.load_cameras(_CAMERA_FILE.value)
    if not -1 <= camera < len(cams):
      raise cli.usage_error(
        f'--camera_index={camera}: {_CAMERA_FILE.value} has {len(cams)} '
        f'cameras; use 0..{len(cams) - 1} (-1: the first)')
    camera = cams[camera if camera >= 0 else 0]
  t0 = time.perf_counter()
  config = RenderConfig(rasterize_mode=_RASTERIZE_MODE.value)
  image = views.render_scene(scene, camera, _WIDTH.value, _HEIGHT.value,
                             background, sh_degree=_SH_DEGREE.value,
                             config=config)
  video.save_png(_OUT.value, image)
  logging.info('%s: %dx%d, %d Gaussians, %.2f s (incl. compile) -> %s',
               scene.name, image.shape[1], image.shape[0],
               scene.gaussians.num, time.perf_counter() - t0, _OUT.value)


if __name__ == '__main__':
  flags.mark_flags_as_required(['scene', 'out'])
  cli.run(main)
