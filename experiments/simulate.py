"""Simulates a 3DGS scene and writes video, frames, trajectory and report.

  python -m experiments.simulate --scene=tabletop --out=out/tabletop
  python -m experiments.simulate --scene=ficus --config.num_frames=24 \\
      --ply --out=out/f
  python -m experiments.simulate --scene=scene.ply --objects=donut \\
      --velocity=donut:0,0,-1 --material_override=donut=jelly --out=out/d

writes ``video.mp4``, ``frames/frame_%04d.png``, ``trajectory.npz``,
``report.json`` and, with ``--ply``, ``ply/frame_%04d.ply`` (with
``--spz``, ``spz/frame_%04d.spz``: Niantic's compressed format, a tenth
of the PLY or less). Settings are the fields of
``physsplat_jax.PipelineConfig`` in ``--config=experiments/configs/simulate.py``
(the default), overridden as ``--config.grid_res=64 --config.render=none``.
With
``--physgaussian=cfg.json`` it runs a PhysGaussian JSON config as
PhysGaussian does. Any error ends in one line ``error: ...`` (exit 1;
``--debug`` shows the traceback).
"""

import os
import sys

from absl import flags
from absl import logging

from experiments.lib import cli
from experiments.lib import profile
from experiments.lib import simulate as lib
from physsplat_jax import perception
from physsplat_jax import pipeline as pl
from physsplat_jax import scenes
from physsplat_jax import segmentation

_CONFIG = cli.define_config_file(
  'config', lib.DEFAULT_CONFIG, 'pipeline config (get_config() of a .py)')
_SCENE = flags.DEFINE_string(
  'scene', 'tabletop', 'built-in scene (tabletop, ficus, donut) or a 3DGS '
  '.ply/.splat/.spz file or output folder')
_OUT = flags.DEFINE_string('out', None, 'output folder')
_OBJECTS = flags.DEFINE_list('objects', None,
                             'only these objects move (the others are fixed)')
_VELOCITY = flags.DEFINE_multi_string(
  'velocity', None, 'NAME:vx,vy,vz initial velocity [m/s] ("*" = all)')
_IMPULSE = flags.DEFINE_multi_string(
  'impulse', None, 'NAME:dvx,dvy,dvz[@t] velocity change over one frame')
_POKE = flags.DEFINE_multi_string(
  'poke', None, 'NAME:ax,ay,az@x,y,z/r[@t0-t1] acceleration [m/s^2] of the '
  "object's particles within r [m] of a point (scene coordinates)")
_SEGMENT = flags.DEFINE_enum(
  'segment', None, list(segmentation.METHODS),
  'segment the scene first (default: keep its objects): auto (--boxes or '
  '--masks if given, else the objects of an object-id property, else '
  'geometric), '
  'attribute, geometric, boxes (--boxes) or masks (--masks)')
_BOXES = flags.DEFINE_string(
  'boxes', None, 'JSON file of boxes, one object each: [{"name": "cup", '
  '"box": [xmin, xmax, ymin, ymax, zmin, zmax], "fixed": false}, ...] in '
  'the scene file\'s coordinates (implies --segment=boxes)')
_MASKS = flags.DEFINE_string(
  'masks', None, 'folder of label masks, one per camera, named after the '
  'camera\'s image (IMG_0012.png): 0 = no object, v >= 1 = object v (or '
  'one colour per object); lifted to the Gaussians (implies --segment=masks)')
_MASK_NAMES = flags.DEFINE_list(
  'mask_names', None, 'names of the objects of --masks, for values 1, 2, '
  '... (default mask_1, mask_2, ...)')
_UP = flags.DEFINE_string(
  'up_axis', None, "scene file: its up axis: x, y, z, -x, -y, -z, a "
  "direction 'x,y,z', or auto (default: from its sidecar, cameras or "
  'dominant plane, else z; reported in report.json)')
_UNITS = flags.DEFINE_float('meters_per_unit', None,
                            'scene file: metres per scene unit')
_MPDP = flags.DEFINE_string('mpdp_checkpoint', None, 'folder of MPDP '
                            'weights (train_mpdp --export) instead of the '
                            'shipped ones')
_PLY = flags.DEFINE_bool('ply', False, 'write per-frame PLY files')
_SPZ = flags.DEFINE_bool('spz', False, 'write per-frame Niantic .spz files '
                         '(spz/frame_%04d.spz, 8-27x smaller than PLY)')
_PHYSGAUSSIAN = flags.DEFINE_string(
  'physgaussian', None, 'a PhysGaussian config/*.json to run as is')
_AUTO = flags.DEFINE_bool('auto_substeps', False, 'PhysGaussian configs: '
                          'replace an unstable substep_dt by a stable one')
_PIPELINED = flags.DEFINE_bool(
  'pipelined', True, 'overlap the host\'s per-frame work (checks, '
  'rendering, writing) with the device simulating the next frame; '
  '--nopipelined runs the stages in turn, for exact per-stage times')
_PROFILE = flags.DEFINE_list(
  'profile_frames', None, 'START,STOP: trace frames START to STOP with '
  'JAX\'s profiler (OUT/profile/) and write the device\'s busy time per '
  'frame, the host\'s wall time per frame and the costliest kernels to '
  'OUT/profile.json (experiments/lib/profile.py)')
flags.mark_flag_as_required('out')
perception.define_flags()


def main(argv):
  del argv
  process = cli.start_run()  # before anything of this run
  sha = lib.git_sha()
  motion = lib.motion_from_flags(_VELOCITY.value, _IMPULSE.value, _POKE.value)
  config = lib.build_config(_SCENE.value, _CONFIG.value, motion=motion,
                            motions=lib.flag_motions())
  if _PHYSGAUSSIAN.value:
    # Its physics, frames and camera come from the JSON (run_physgaussian).
    logging.info('git %s, PhysGaussian config %s; from --config: fill=%s, '
                 'render=%s, %dx%d', sha, _PHYSGAUSSIAN.value, config.fill,
                 config.render, config.width, config.height)
    _check_physgaussian_flags()
    if not os.path.isfile(_PHYSGAUSSIAN.value):
      raise cli.usage_error(
        f'--physgaussian={_PHYSGAUSSIAN.value}: no such file; give the path '
        'of a PhysGaussian .json config (e.g. '
        'experiments/configs/jelly_drop.json)')
    if not os.path.isfile(_SCENE.value):
      what = ('a built-in scene' if _SCENE.value in scenes.list_scenes()
              else 'a folder' if os.path.isdir(_SCENE.value)
              else 'no such file')
      raise cli.usage_error(
        f'--physgaussian runs its JSON on a trained 3DGS PLY, and '
        f'--scene={_SCENE.value} is {what}: give --scene=FILE.ply, the '
        'Gaussians the JSON was written for')
    lib.run_physgaussian(_SCENE.value, _PHYSGAUSSIAN.value, _OUT.value,
                         config, ply=_PLY.value, spz=_SPZ.value,
                         auto_substeps=_AUTO.value)
    print(f'wrote {_OUT.value}')
    return
  logging.info('git %s, config %s', sha, config)
  window = _profile_window(config)
  try:
    report = lib.run_scene(
      _SCENE.value, config, _OUT.value, objects=_OBJECTS.value or (),
      ply=_PLY.value, spz=_SPZ.value, segment=_segment_method(),
      boxes=_BOXES.value,
      masks=_MASKS.value, mask_names=_MASK_NAMES.value,
      perception_options=lib.perception_options_from_flags(),
      scene_options=dict(up_axis=_UP.value, meters_per_unit=_UNITS.value),
      mpdp_checkpoint=_MPDP.value, pipelined=_PIPELINED.value,
      extra_report=dict(command=' '.join(sys.argv), git=sha),
      process=process, on_frame=window)
  finally:
    if window is not None:
      window.close()
  print(pl.summary(report))
  if window is not None:
    got = window.summary()
    cli.write_json(os.path.join(_OUT.value, 'profile.json'), got)
    if got:
      print(f'profile, frames {got["frames"][0]}-{got["frames"][1]} '
            f'({got["device"]}): {got["wall_ms"]:.1f} ms wall and '
            f'{got["busy_ms"]:.1f} ms device-busy per frame, '
            f'{got["launches"]:.0f} kernels per frame')


def _segment_method() -> str | None:
  """--segment, implied by --boxes / --masks, checked against them."""
  method = _SEGMENT.value
  given = [f for f, v in (('boxes', _BOXES.value), ('masks', _MASKS.value))
           if v is not None]
  if len(given) > 1:
    raise cli.usage_error('--boxes and --masks both given: segment with one '
                          'of them')
  if _MASK_NAMES.value and not _MASKS.value:
    raise cli.usage_error('--mask_names names the objects of --masks; give '
                          '--masks=FOLDER too')
  if given:
    if method not in (None, 'auto', given[0]):
      raise cli.usage_error(
        f'--segment={method} with --{given[0]}: drop --segment (--'
        f'{given[0]} implies --segment={given[0]})')
    return given[0]
  if method in ('boxes', 'masks'):
    what = ('--boxes=FILE.json' if method == 'boxes'
            else '--masks=FOLDER of label images')
    raise cli.usage_error(f'--segment={method} needs {what}')
  return method


# What a PhysGaussian JSON run takes from the command line besides the
# scene and --out: the rest of the run is the JSON's.
_PHYSGAUSSIAN_FLAGS = ('scene', 'out', 'physgaussian', 'auto_substeps',
                       'ply', 'spz', 'config')
_PHYSGAUSSIAN_CONFIG = ('fill', 'render', 'width', 'height')


def _check_physgaussian_flags() -> None:
  """A flag that --physgaussian would ignore is a usage error (it ran the
  JSON's frames, materials and motion without a word)."""
  own = set(flags.FLAGS.get_key_flags_for_module(sys.modules[__name__]))
  own |= {flags.FLAGS[n] for n in flags.FLAGS if n.startswith(
    ('material_', 'default_material', 'perception_', 'mllm_'))}
  ignored = sorted(f'--{f.name}' for f in own
                   if f.present and f.name not in _PHYSGAUSSIAN_FLAGS)
  ignored += sorted(
    a.split('=')[0] for a in sys.argv[1:] if a.startswith('--config.')
    and a.split('=')[0][len('--config.'):] not in _PHYSGAUSSIAN_CONFIG)
  if ignored:
    raise cli.usage_error(
      f'--physgaussian runs its JSON as PhysGaussian does, so '
      f'{", ".join(ignored)} would be ignored: set these in the JSON '
      '(frame_num, materials, boundary conditions), or drop --physgaussian. '
      'It takes --scene, --out, --ply, --spz, --auto_substeps and '
      f'{", ".join("--config." + k for k in _PHYSGAUSSIAN_CONFIG)}.')


def _profile_window(config):
  """The ``--profile_frames`` hook, or None."""
  if not _PROFILE.value:
    return None
  try:
    start, stop = (int(v) for v in _PROFILE.value)
  except ValueError:
    start = stop = -1
  if not 0 <= start < stop < config.num_frames + 1:
    raise cli.usage_error(
      f'--profile_frames: {",".join(_PROFILE.value)} is not START,STOP with '
      f'0 <= START < STOP <= {config.num_frames} (the run\'s frames)')
  return profile.FrameWindow(start, stop,
                             os.path.join(_OUT.value, 'profile'))


if __name__ == '__main__':
  cli.run(main, cpu_devices=2, fast_exit=True)
