"""The whole job on one scene: segment, perceive, prepare, simulate, write.

:func:`simulate_scene` is what ``make demo`` and ``experiments/simulate.py``
run. It checks the output folder before any expensive work and always
writes ``report.json`` (atomically), also when the run fails: the failure
is in the report and the files written so far are complete.
"""

from __future__ import annotations

import dataclasses
import os
import time
from typing import Any, Callable, Sequence

import jax
from absl import logging

from physsplat_jax import perception
from physsplat_jax import segmentation
from physsplat_jax.io import outputs as out_lib
from physsplat_jax.pipeline.config import PipelineConfig
from physsplat_jax.pipeline.config import PipelineError
from physsplat_jax.pipeline.host import RunOutput
from physsplat_jax.pipeline.host import run
from physsplat_jax.pipeline.prepare import prepare_scene
from physsplat_jax.pipeline.simulation import init_params
from physsplat_jax.segmentation.attributes import find_attribute
from physsplat_jax.types import Scene


def select_objects(scene: Scene, names: Sequence[str]) -> Scene:
  """Marks every object not in ``names`` as fixed (only these move)."""
  known = [o.name for o in scene.objects]
  missing = [n for n in names if n not in known]
  if missing:
    raise PipelineError(f'objects {missing} are not in scene {scene.name!r}; '
                        f'objects: {known}')
  objs = tuple(dataclasses.replace(o, fixed=o.fixed or o.name not in names)
               for o in scene.objects)
  return scene.replace(objects=objs)


def segment_stage(scene: Scene, method: str | None, **inputs) -> Scene:
  """Segments ``scene`` into objects with ``method`` (None: keep its own).

  Scenes that come segmented (built-ins, PLYs with an object-id property)
  keep their objects; a method ('auto', 'geometric', ...; see
  :mod:`physsplat_jax.segmentation`) replaces them.

  Args:
    scene: the scene.
    method: a :data:`physsplat_jax.segmentation.METHODS` entry, or None.
    **inputs: the method's inputs for :func:`physsplat_jax.segmentation.
      segment`: ``boxes=`` (and ``names=``, ``fixed=``) for 'boxes',
      ``masks=`` (and ``names=``; ``cameras=`` default the scene's) for
      'masks' (:mod:`physsplat_jax.io.segment_inputs` reads both from files).
  """
  if method is None:
    return scene
  if (method in ('attribute', 'auto') and not inputs
      and find_attribute(scene.gaussians) is None
      and _segmented_on_load(scene)):
    # load_scene moved the file's object-id property into object_ids (and
    # out of the Gaussians' extras): 'attribute' found none, and 'auto'
    # replaced the file's objects with the geometric method's.
    logging.info('segment %r: scene %r keeps the %d objects of its '
                 'object-id property (read when loaded): %s', method,
                 scene.name, len(scene.objects),
                 ', '.join(o.name for o in scene.objects))
    return scene
  if inputs.get('masks') is not None and inputs.get('cameras') is None:
    inputs['cameras'] = scene.cameras
  seg = segmentation.segment(scene.gaussians, method, up=scene.up_vector,
                             **inputs)
  segmented = seg.to_scene(scene.gaussians, cameras=scene.cameras,
                           up_axis=scene.up_axis,
                           meters_per_unit=scene.meters_per_unit,
                           name=scene.name)
  logging.info('segmented %r with %r: %d objects (%s)', scene.name, method,
               len(segmented.objects),
               ', '.join(o.name for o in segmented.objects))
  if not any(not o.fixed for o in segmented.objects):
    # (prepare_scene's message spoke of ObjectInfo.fixed, which a script
    # user does not set.)
    found = ', '.join(f'{o.name} (fixed)' for o in segmented.objects)
    raise PipelineError(
      f'segmenting scene {scene.name!r} with {method!r} found '
      f'{found or "no object"}: nothing to move. Try another method '
      f'({", ".join(m for m in segmentation.METHODS if m != method)}; '
      'boxes and masks need their boxes or masks: experiments.simulate '
      '--boxes / --masks, segment_stage(..., boxes=) / (masks=)), '
      'or a scene whose objects stand apart from the support.')
  return segmented


def _segmented_on_load(scene: Scene) -> bool:
  """The scene's objects came with it (a file's object-id property, a
  sidecar, a built-in scene), not the single default object."""
  return len(scene.objects) > 1 or any(
    t.startswith('ply_id=') for o in scene.objects for t in o.tags)


# (report.json checked before the work too: a folder in its place failed at
# the end of a finished run)
@out_lib.holds_output_dir('report.json')
def simulate_scene(
  scene: Scene,
  config: PipelineConfig,
  out_dir: str | None = None,
  *,
  materials: Sequence[Any] | None = None,
  perception_options: Any = None,
  segment: str | None = None,
  ply: bool = False,
  spz: bool = False,
  extra_report: dict | None = None,
  mpdp_params: Any = None,
  pipelined: bool = True,
  on_frame: Callable | None = None,
) -> tuple[RunOutput, dict]:
  """The whole job on one scene.

  Args:
    scene: the scene (``physsplat_jax.load_scene``).
    config: pipeline settings (``config.seed`` makes the PRNG key).
    out_dir: where ``video.mp4``, ``frames/``, ``trajectory.npz``,
      ``report.json`` (and ``ply/``, ``spz/``) go; None writes nothing.
    materials: one material per object; None runs perception
      (``physsplat_jax.perception.perceive_scene`` with
      ``perception_options``; offline library by default).
    perception_options: ``perception.PerceptionOptions``.
    segment: segmentation method for an unsegmented scene (None keeps the
      scene's objects).
    ply: also write per-frame PLY files (``ply/frame_%04d.ply``).
    spz: also write per-frame Niantic .spz files (``spz/frame_%04d.spz``,
      a tenth of a PLY frame or less).
    extra_report: merged into ``report.json`` (e.g. the command line).
    mpdp_params: MPDP weights (e.g. a user's checkpoint from
      ``physsplat_jax.mpdp.load_params``); default the shipped ones.
    pipelined: overlap host and device work frame by frame (see
      :func:`~physsplat_jax.pipeline.run`); False for exact per-stage
      times.
    on_frame: optional ``callback(frame, means, image)`` after each frame
      is handed to the writers (:func:`~physsplat_jax.pipeline.run`).

  Returns:
    (:class:`RunOutput`, the report dict).

  Raises:
    The stage's own error (PipelineError, SimulationError, OutputError, ...)
    after ``report.json`` records it.
  """
  if not isinstance(config, PipelineConfig):
    raise PipelineError(
      f'simulate_scene: config must be a PipelineConfig (all settings, '
      f'flat), got {type(config).__name__}; e.g. PipelineConfig(num_frames='
      '24, grid_res=32)')
  stages: dict[str, float] = {}
  report: dict[str, Any] = dict(
    scene=scene.name, num_frames=config.num_frames, fps=config.fps,
    devices=[str(d) for d in jax.devices()],
    device_kind=jax.devices()[0].device_kind, jax_version=jax.__version__,
    config=dataclasses.asdict(config), **(extra_report or {}))
  t0 = time.perf_counter()
  started = time.time()
  try:
    out = _run_stages(scene, config, out_dir, materials, perception_options,
                      segment, (ply, spz), stages, report, mpdp_params,
                      pipelined, on_frame)
  except (Exception, KeyboardInterrupt) as e:
    # (Ctrl-C too: the frames so far stay, and without this a report.json
    # of an earlier run in out_dir went on describing them.)
    report['error'] = (f'{type(e).__name__}: {e}' if str(e) else
                       type(e).__name__)
    stages['total'] = time.perf_counter() - t0
    report['stage_seconds'] = {k: round(v, 3) for k, v in stages.items()}
    _note_earlier_outputs(out_dir, started, report)
    if out_dir is not None:
      out_lib.write_failure_report(os.path.join(out_dir, 'report.json'),
                                   report)
    raise
  stages['total'] = time.perf_counter() - t0
  _note_earlier_outputs(out_dir, started, report, written=out.files)
  report['stage_seconds'] = {k: round(v, 3) for k, v in stages.items()}
  report['files'] = dict(out.files)
  path = _write_report(out_dir, report)
  if path:
    out.files['report'] = path
    report['files'] = dict(out.files)
  return out, report


def _run_stages(scene, config, out_dir, materials, perception_options,
                segment, frames, stages, report, mpdp_params,
                pipelined, on_frame=None) -> RunOutput:
  t = time.perf_counter()
  scene = segment_stage(scene, segment)
  stages['segmentation'], t = time.perf_counter() - t, time.perf_counter()
  if materials is None:
    materials = perception.perceive_scene(scene, perception_options)
  stages['perception'], t = time.perf_counter() - t, time.perf_counter()
  key = jax.random.PRNGKey(config.seed)
  prepared, prep = prepare_scene(key, scene, materials, config, mpdp_params)
  params = init_params(prepared, config, mpdp_params)
  stages['prepare'] = time.perf_counter() - t
  stages.update({f'prepare.{k[:-2]}': v for k, v in prep.timings.items()})
  objects = []
  for o, m in zip(prep.objects, materials):
    d = m.to_dict() if hasattr(m, 'to_dict') else dataclasses.asdict(m)
    objects.append({**o, 'material': d})
  report.update(
    objects=objects, colliders=prep.colliders,
    num_gaussians=prep.num_gaussians,
    num_simulated_gaussians=prep.num_simulated_gaussians,
    num_candidates=prep.num_candidates, num_particles=prep.num_particles,
    grid=prep.grid, time_step=prep.time_step, capture=prep.capture)
  field = prepared.field if config.use_mpdp else None
  report['pipelined'] = pipelined
  ply, spz = frames
  out = run(params, prepared, config, out_dir=out_dir, ply=ply, spz=spz,
            field=field, pipelined=pipelined, on_frame=on_frame)
  stages.update(out.timings)
  stages.pop('total', None)
  report['particle_substeps_per_s'] = out.particle_substeps_per_s
  if out.render_stats:
    report['render_stats'] = out.render_stats
  return out


# What a run writes into its folder (report.json is always rewritten).
_OUTPUTS = ('video.mp4', 'video.gif', 'trajectory.npz', 'frames', 'ply',
            'spz')


def _note_earlier_outputs(out_dir, started: float, report: dict,
                          written: dict | None = None) -> None:
  """Names in ``report['earlier_files']``, with a warning, the outputs in
  ``out_dir`` that this run did not write: a failed rerun, or one without
  ``ply``, left an earlier run's video or PLY folder beside the new
  report, with nothing to tell them apart. They are kept (never lost).
  ``written``: the run's files (``RunOutput.files``) when it finished;
  else the files' modification times against ``started`` decide."""
  if out_dir is None:
    return
  ours = {os.path.realpath(p) for p in (written or {}).values()}
  old = []
  for name in _OUTPUTS:
    path = os.path.join(out_dir, name)
    try:
      if written is not None:
        if os.path.exists(path) and os.path.realpath(path) not in ours:
          old.append(name)
      elif os.path.isdir(path):
        times = [e.stat().st_mtime for e in os.scandir(path) if e.is_file()]
        if times and max(times) < started:
          old.append(name)
      elif os.path.isfile(path) and os.stat(path).st_mtime < started:
        old.append(name)
    except OSError:
      continue
  if old:
    report['earlier_files'] = old
    logging.warning('%s still holds %s from an earlier run, not written by '
                    'this one (report.json: earlier_files); remove them, or '
                    'give a new --out, to keep runs apart', out_dir,
                    ', '.join(old))


def _write_report(out_dir, report) -> str | None:
  if out_dir is None:
    return None
  return out_lib.write_json(os.path.join(out_dir, 'report.json'), report)


def summary(report: dict) -> str:
  """A short human summary of a :func:`simulate_scene` report."""
  st = report['stage_seconds']
  total = max(st.get('total', 0.0), 1e-9)
  main = ['segmentation', 'perception', 'prepare', 'compile', 'simulate',
          'deform', 'render', 'write']
  parts = ', '.join(
    f'{k} {st.get(k, 0.0):.1f} s ({100 * st.get(k, 0.0) / total:.0f}%)'
    for k in main if st.get(k, 0.0) >= 0.05 or k in ('simulate', 'render'))
  lines = [
    f'{report["scene"]}: {report["num_frames"]} frames, '
    f'{report["num_particles"]} particles driving '
    f'{report["num_simulated_gaussians"]} of {report["num_gaussians"]} '
    f'Gaussians, {report["time_step"]["substeps_per_frame"]} substeps/frame, '
    f'{report["particle_substeps_per_s"] / 1e6:.2f} M particle-substeps/s',
    f'time {total:.1f} s: {parts}',
  ]
  if (report.get('pipelined')
      and sum(st.get(k, 0.0) for k in main) > 1.05 * total):
    # Pipelined, deform and render are the host's waits and frame 0's
    # compiles on a second thread, beside 'compile': a sum of 147% read
    # as a bookkeeping error.
    lines.append('(pipelined: the stages overlap, so they add up to more '
                 'than the total; --nopipelined times them one by one)')
  proc = report.get('process_seconds')
  if proc:  # what a script spent before the pipeline (experiments.simulate)
    start = ('' if proc.get('start') is None
             else f'{proc["start"]:.1f} s to start (Python, imports), ')
    seg = ('' if proc.get('segment') is None
           else f', {proc["segment"]:.1f} s to segment it')
    lines.append(f'before it: {start}{proc.get("setup", 0.0):.1f} s to set '
                 f'up (config, JAX\'s backend, reading the scene){seg}')
  for f, p in sorted(report.get('files', {}).items()):
    lines.append(f'  {f}: {p}')
  return '\n'.join(lines)
