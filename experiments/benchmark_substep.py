"""Where a scene's MLS-MPM substep spends its time (variants, one process).

  python -m experiments.benchmark_substep                  # tabletop, demo
  python -m experiments.benchmark_substep --scene=ficus --out=sub.json
  python -m experiments.benchmark_substep --scene=donut --preset=paper

Prepares the scene with the `make demo` settings (experiments/configs/
demo.py; ``--preset=paper``: the paper's, 64^3 and up to 200k particles, as
``benchmark_pipeline --preset=paper`` simulates it), then times one frame
of ``--substeps`` substeps from the initial state for each variant of the
static MPM config (experiments/lib/substep.py: ``scene``, the pipeline's
grouped substep; ``split``, the same with a constitutive slice per model on a
GPU too; ``masked``; ``no_plane``; ``no_plane_no_body``; ``bare``, one
fixed-corotated material with no body and no plane), all compiled first and
timed in turns (best of ``--rounds``). ``--constitutive_kernels=auto,jax``
times each variant with the stress update as one Pallas kernel (on a CUDA GPU)
and as XLA's fusion, in the same process; ``--gpu_graphs=substep,frame,off``
with the frame launched on a GPU as one CUDA graph per substep (XLA's default),
as one graph and with none (``SimConfig.gpu_graphs``).

The differences say what the materials, the rigid bodies and the plane
contact cost per substep. ``--clock=cpu`` reports process CPU time instead
of wall time (steadier on a shared machine). ``--profile`` then runs each
variant once more under JAX's profiler and reports the device's busy time
per substep (summed kernel time; of the untraced wall time above, the rest
is launch gaps and the host),
the kernels it launched, and the most expensive ones with the name scopes
they came from (experiments/lib/profile.py). Figures: docs/benchmarks.md.
"""

import dataclasses
import tempfile
import time

import jax
import jax.numpy as jnp
from absl import flags

from experiments.lib import cli
from experiments.lib import hlo
from experiments.lib import profile
from experiments.lib import substep as substep_lib
from physsplat_jax import mpm
from physsplat_jax.mpm import graphs

_SCENE = flags.DEFINE_string('scene', 'tabletop', 'built-in scene or PLY')
_PRESET = substep_lib.define_preset()
_SUBSTEPS = flags.DEFINE_integer('substeps', 40, 'substeps per timed call',
                                 lower_bound=1)
_ROUNDS = flags.DEFINE_integer('rounds', 5, 'timed calls per variant',
                               lower_bound=1)
_VARIANTS = flags.DEFINE_list(
  'variants', [v for v in substep_lib.VARIANTS if v != 'split'],
  f'variants to time, of {", ".join(substep_lib.VARIANTS)}')
_CLOCK = flags.DEFINE_enum('clock', 'wall', ['wall', 'cpu'], 'what to time')
_OUT = flags.DEFINE_string('out', None, 'JSON file for the results')
_START_FRAME = flags.DEFINE_integer(
  'start_frame', 0, 'time from the state after this many frames of the '
  'scene (objects resting on the support) instead of its initial state',
  lower_bound=0)
_PROFILE = flags.DEFINE_boolean(
  'profile', False, 'also trace each variant once: device-busy time per '
  'substep and the most expensive kernels')
_TOP = flags.DEFINE_integer('top', 12, '--profile: kernels listed per variant',
                            lower_bound=1)
_KERNELS = flags.DEFINE_list(
  'constitutive_kernels', ['auto'], 'SimConfig.constitutive_kernel values '
  "(auto, jax, pallas); with more than one, each variant runs with each, "
  "named VARIANT@KERNEL (auto: the stress update as one Pallas kernel on "
  "a CUDA GPU)")
_GRAPHS = flags.DEFINE_list(
  'gpu_graphs', ['substep'], 'SimConfig.gpu_graphs values (substep, frame, '
  'off): how a CUDA GPU launches the timed frame (one CUDA graph per '
  'substep, one for the loop, none); with more than one, each variant runs '
  'with each, named VARIANT@GRAPHS (the CPU ignores them)')


def _profile(name, fn, args, substeps):
  """One traced call of a variant's compiled frame, per substep."""
  labels = hlo.kernel_labels(fn.as_text())
  with tempfile.TemporaryDirectory() as logdir:
    _, path = profile.trace(lambda: fn(*args), logdir)
    got = profile.per_call(profile.kernel_times(path), substeps, labels,
                           _TOP.value)
  print(f'{name}: device {got["device"]}, busy {got["busy_us"]:.1f} us and '
        f'{got["launches"]:.1f} launches per substep')
  for k in got['top']:
    print(f'  {k["us"]:8.2f} us  x{k["launches"]:<5.2f} {k["kernel"]:40s} '
          f'{k["label"]}')
  return got


def main(argv):
  del argv
  # The flags first: they were checked after the scene's preparation.
  bad = sorted(set(_VARIANTS.value) - set(substep_lib.VARIANTS))
  if bad or not _VARIANTS.value:
    raise cli.usage_error(f'--variants: unknown {bad or "(none given)"}; '
                          f'use some of {", ".join(substep_lib.VARIANTS)}')
  kernels = _KERNELS.value
  bad = sorted(set(kernels) - set(mpm.CONSTITUTIVE_KERNELS))
  if bad:
    raise cli.usage_error(f'--constitutive_kernels: unknown {bad}; use '
                          f'{", ".join(mpm.CONSTITUTIVE_KERNELS)}')
  launches = _GRAPHS.value
  bad = sorted(set(launches) - set(mpm.GPU_GRAPHS))
  if bad:
    raise cli.usage_error(f'--gpu_graphs: unknown {bad}; use '
                          f'{", ".join(mpm.GPU_GRAPHS)}')
  cli.check_output_file('out', _OUT.value)
  prepared, state, mats, forces, sim_config = (
    substep_lib.demo_scene_state(_SCENE.value, _PRESET.value))
  if _START_FRAME.value > 0:
    advance = jax.jit(mpm.make_frame(sim_config))
    for _ in range(_START_FRAME.value):
      state = advance(state, mats, forces)
  sim_config = dataclasses.replace(sim_config,
                                   substeps_per_frame=_SUBSTEPS.value)
  n = prepared.num_particles
  clock = time.perf_counter if _CLOCK.value == 'wall' else time.process_time
  runs = {}
  for kernel in kernels:
    for graph in launches:
      for name in _VARIANTS.value:
        s, m, f, c = substep_lib.variant(name, state, mats, forces,
                                         sim_config)
        c = dataclasses.replace(c, constitutive_kernel=kernel)
        fn = graphs.compile_frame(
          jax.jit(substep_lib.make_frame(name, c)).lower(s, m, f), graph)
        out = fn(s, m, f)
        jax.block_until_ready(out)
        label = name + (f'@{kernel}' if len(kernels) > 1 else '') + (
          f'@{graph}' if len(launches) > 1 else '')
        runs[label] = (fn, out, m, f)
  best = {name: float('inf') for name in runs}
  for _ in range(_ROUNDS.value):
    for name, (fn, s, m, f) in runs.items():
      t = clock()
      jax.block_until_ready(fn(s, m, f))
      best[name] = min(best[name], (clock() - t) / _SUBSTEPS.value)
  rows = []
  for name, sec in best.items():
    finite = bool(jnp.all(jnp.isfinite(runs[name][1].x)))
    rows.append(dict(variant=name, ms_per_substep=1e3 * sec,
                     m_particle_substeps_per_s=n / sec / 1e6, finite=finite))
    print(f'{name:18s} {1e3 * sec:7.3f} ms/substep  '
          f'{n / sec / 1e6:5.2f} M particle-substeps/s ({_CLOCK.value})'
          + ('' if finite else '  (went non-finite: timing not meaningful)'))
  if _PROFILE.value:
    for row in rows:
      fn, s, m, f = runs[row['variant']]
      row['profile'] = _profile(row['variant'], fn, (s, m, f),
                                _SUBSTEPS.value)
      row['profile']['busy_fraction'] = (
        row['profile']['busy_us'] / 1e3 / row['ms_per_substep'])
  result = dict(scene=_SCENE.value, start_frame=_START_FRAME.value,
                particles=n, models=sim_config.models,
                num_bodies=sim_config.num_bodies, clock=_CLOCK.value,
                substeps=_SUBSTEPS.value, devices=[str(d) for d in
                                                   jax.devices()],
                jax_version=jax.__version__, machine=cli.machine(),
                rows=rows)
  cli.write_json(_OUT.value, result)


if __name__ == '__main__':
  cli.run(main, cache_default='off')
