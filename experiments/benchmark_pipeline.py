"""Whole-pipeline timings per stage, with a cold and a warm compile cache.

  python -m experiments.benchmark_pipeline --out=out/bench_pipeline
  python -m experiments.benchmark_pipeline --preset=paper --scenes=donut

Runs ``experiments.simulate`` once per scene in a fresh process with an
empty compilation cache (cold) and once more with the cache it filled
(warm), then writes ``pipeline.json``: per scene and run, the stage times
from ``report.json`` (segmentation, perception, prepare and its stages,
compile, simulate, deform, render, write, total), the process wall time,
particle counts and substeps. ``--runs=cold,warm,serial`` adds a third
run, warm (a scene's runs share its cache), with the host loop unpipelined
(``--nopipelined``): its stage times are exact, and its total against the
warm run's is what the pipelining saves; ``profile`` adds a warm,
pipelined run traced over ``--profile_frames`` (``experiments.simulate
--profile_frames``): per frame, the host's wall time, the device's busy
time and the costliest kernels, apart from the timed runs. A run may carry
its own overrides after an ``@`` (``warm@render_config.backend=jax``,
several joined by ``+``): on a warm cache only the programs they change
compile again. Presets: ``paper`` is the paper's
setting (64^3 grid, 768 substeps per frame at 30 fps, 150 frames = a 5 s video,
800x800, up to 200k particles) for a GPU; ``cpu`` is sized for a 2-core
CPU (the ``make demo`` settings).
"""

import json
import os
import shutil
import sys
import tempfile
import time

from absl import flags

from experiments.lib import cli
from experiments.lib.presets import PRESETS
from physsplat_jax.io import outputs
from physsplat_jax.pipeline import PipelineError


_OUT = flags.DEFINE_string('out', 'out/bench_pipeline', 'output folder')
_SCENES = flags.DEFINE_list('scenes', ['tabletop', 'ficus', 'donut'],
                            'scenes (built-in names or PLY paths)')
_PRESET = flags.DEFINE_enum('preset', 'cpu', sorted(PRESETS), 'settings')
_RUNS = flags.DEFINE_list(
  'runs', ['cold', 'warm'], 'in order, sharing one compile cache per scene: '
  'cold, warm, serial (--nopipelined: exact per-stage times; warm when a '
  'run before it filled the cache) and/or profile (traced frames); '
  'KIND@KEY=VALUE[+KEY=VALUE] adds overrides to one run, e.g. '
  'warm@render_config.backend=jax; a run named twice runs twice (the '
  'second is reported as warm#2)')
_PROFILE_FRAMES = flags.DEFINE_list(
  'profile_frames', None, 'START,STOP: the frames the profile run traces '
  '(default the middle third of the run)')
_SET = flags.DEFINE_list(
  'set', [], 'extra config overrides for every run, KEY=VALUE as after '
  '--config. (e.g. render_config.backend=jax); they win over the preset')


def run_once(scene: str, preset: dict, out: str, cache: str,
             pipelined: bool = True, overrides: dict | None = None,
             profile_frames: str | None = None) -> dict:
  """One ``experiments.simulate`` process; its report plus the wall time
  (and its ``profile.json`` with ``profile_frames``)."""
  cmd = [sys.executable, '-m', 'experiments.simulate', f'--scene={scene}',
         f'--out={out}', f'--compile_cache={cache}',
         '--pipelined' if pipelined else '--nopipelined']
  if profile_frames:
    cmd.append(f'--profile_frames={profile_frames}')
  settings = {**preset, **(overrides or {})}
  cmd += [f'--config.{k}={v}' for k, v in settings.items()]
  t0 = time.perf_counter()
  proc = cli.run_child(cmd)
  wall = time.perf_counter() - t0
  if proc.returncode != 0:
    return dict(error=[cli.last_error(proc.stderr)], wall_s=wall)
  with open(os.path.join(out, 'report.json')) as f:
    report = json.load(f)
  extra = {}
  if profile_frames:
    with open(os.path.join(out, 'profile.json')) as f:
      extra['profile'] = json.load(f)
  proc = dict(report.get('process_seconds') or {})
  if proc:
    # What the report does not cover: the process's end (writers' files
    # closed, JAX and Python shutting down) and the time to launch it.
    known = (proc.get('start') or 0.0) + proc.get('setup', 0.0)
    proc['after'] = round(wall - known - report['stage_seconds']['total'], 3)
  return dict(wall_s=round(wall, 2), stage_seconds=report['stage_seconds'],
              process_seconds=proc,
              num_particles=report['num_particles'],
              num_gaussians=report['num_gaussians'],
              substeps_per_frame=report['time_step']['substeps_per_frame'],
              particle_substeps_per_s=report['particle_substeps_per_s'],
              render_stats=report.get('render_stats'),
              devices=report['devices'],
              device_kind=report.get('device_kind'), **extra)


def _pairs(what: str, items) -> dict:
  """``KEY=VALUE`` items as a dict (a usage error naming ``what``)."""
  pairs = {}
  for item in items:
    key, sep, value = item.partition('=')
    if not sep or not key:
      raise cli.usage_error(f'{what}: {item!r} is not KEY=VALUE (e.g. '
                            'render_config.backend=jax)')
    pairs[key] = value
  return pairs


def main(argv):
  del argv
  preset = PRESETS[_PRESET.value]
  overrides = _pairs('--set', _SET.value)
  specs = {}
  for run in _RUNS.value:
    kind, _, extra = run.partition('@')
    if kind not in ('cold', 'warm', 'serial', 'profile'):
      raise cli.usage_error(
        f'--runs: {run!r} is not cold, warm, serial or profile (each with '
        'optional @KEY=VALUE overrides)')
    # A run named twice runs twice (warm, warm#2: the spread of warm runs).
    name, i = run, 1
    while name in specs:
      i += 1
      name = f'{run}#{i}'
    specs[name] = (kind, _pairs(f'--runs {run}',
                                extra.split('+') if extra else []))
  frames = int(overrides.get('num_frames', preset['num_frames']))
  window = ','.join(_PROFILE_FRAMES.value or
                    [str(frames // 3), str(max(2 * frames // 3, 1))])
  outputs.check_output_dir(_OUT.value)  # (a file there: named, at once)
  # (not JAX's devices: this process leaves the GPU to the runs; each
  # run has its device_kind)
  results = dict(preset=_PRESET.value, settings=preset, overrides=overrides,
                 machine=cli.machine(devices=False), scenes={})
  for scene in _SCENES.value:
    cache = tempfile.mkdtemp(prefix='physsplat_cache_')
    try:
      runs = {}
      for run, (kind, extra) in specs.items():
        out = os.path.join(_OUT.value, os.path.basename(scene),
                           run.replace('@', '_').replace('+', '_')
                           .replace('#', '_'))
        runs[run] = run_once(
          scene, preset, out, cache, pipelined=kind != 'serial',
          overrides={**overrides, **extra},
          profile_frames=window if kind == 'profile' else None)
        if extra:
          runs[run]['overrides'] = extra
        if 'error' in runs[run]:
          print(f'{scene} {run}: failed: {" ".join(runs[run]["error"])}',
                flush=True)
        else:
          print(f'{scene} {run}: {runs[run].get("wall_s")} s', flush=True)
      results['scenes'][scene] = runs
    finally:
      shutil.rmtree(cache, ignore_errors=True)
  path = os.path.join(_OUT.value, 'pipeline.json')
  cli.write_json(path, results)
  print(json.dumps(results, indent=1))
  failed = [f'{scene} {run}: {" ".join(r["error"])}'
            for scene, runs in results['scenes'].items()
            for run, r in runs.items() if 'error' in r]
  if failed:
    # The runs that worked are in pipeline.json; the exit code says not all.
    raise PipelineError(f'{len(failed)} run(s) failed ({path} has the '
                        f'rest): {"; ".join(failed)}')


if __name__ == '__main__':
  cli.run(main)
