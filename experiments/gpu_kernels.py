"""Kernels per MLS-MPM substep on a GPU, counted without a GPU.

  python -m experiments.gpu_kernels                       # tabletop, H100
  python -m experiments.gpu_kernels --scene=ficus --out=k.json
  python -m experiments.gpu_kernels --targets=render     # Pallas kernels

On a GPU a substep of a few thousand particles is bound by the number of
kernels it launches, not by arithmetic (docs/benchmarks.md). XLA can compile
for a GPU it does not see ("deviceless" compilation, a ``target_config``
topology): this script prepares the scene with the `make demo` settings
(experiments/configs/demo.py; ``--preset=paper``: the paper's, as
``benchmark_pipeline --preset=paper`` runs it), compiles one frame of the
MPM for the GPU described by ``--spec`` (an XLA ``GpuTargetConfigProto``;
default an H100 SXM, experiments/configs/gpu_specs/), and counts in the
optimised program the kernels of the substep: every instruction of the scan's
body that XLA emits as a kernel (fusions, copies, custom calls, sorts, ...),
and, for a loop nested in it, its body's kernels times its trip count. The
variants (``scene``, ``masked``, ``no_plane``, ``no_plane_no_body``, ``bare``)
are ``benchmark_substep``'s (experiments/lib/substep.py). ``--targets=render``
compiles the Pallas (Triton) compositor of the renderer, forward and
gradient, for the same GPU: that its kernels build for the device at all,
and, where NVIDIA's ``ptxas`` is found (the ``nvidia-cuda-nvcc`` wheel of a
CUDA jaxlib), each kernel's registers, spills and resident warps per SM
(experiments/lib/ptxas.py; ``--render_block`` etc. set the kernels' blocks);
``--targets=simulate`` the whole differentiable ``simulate`` of the scene
(MPDP field, MPM, deformation, rendering) and its gradient.

Needs a CUDA build of jaxlib installed, e.g. ``pip install 'jax[cuda13]'``
(the CUDA libraries come as wheels; no GPU or driver needed), in an
environment of its own if the CPU one must stay as it is; run it with
``JAX_PLATFORMS=cpu``. Counts are structure, not time: what one kernel costs
on the device is in docs/benchmarks.md.
"""

from __future__ import annotations

import os

# Without the device XLA cannot autotune, and jax 0.10.2's default Triton
# GEMM configuration fails to compile dots fused with their neighbours
# ("Couldn't find output tile sizes", seen on a Flax Dense layer as on
# G2P's product): such dots go to cuBLAS here, one kernel either way.
os.environ.setdefault('XLA_FLAGS', '--xla_gpu_enable_triton_gemm=false')

import dataclasses  # noqa: E402
import pathlib
import shutil
import tempfile
import time

import jax
import jax.numpy as jnp
from absl import flags
from absl import logging

from experiments.lib import cli
from experiments.lib import hlo
from experiments.lib import ptxas as ptxas_lib
from experiments.lib import substep as substep_lib
from physsplat_jax import mpm
from physsplat_jax import platforms
from physsplat_jax import pipeline as pl
from physsplat_jax.errors import PhysSplatError
from physsplat_jax.render import pallas_raster
from physsplat_jax.render.config import RenderConfig

SPECS = pathlib.Path(__file__).parent / 'configs' / 'gpu_specs'

_SCENE = flags.DEFINE_string('scene', 'tabletop', 'built-in scene or PLY')
_PRESET = substep_lib.define_preset()
_SPEC = flags.DEFINE_string(
  'spec', str(SPECS / 'h100_sxm.txtpb'),
  'XLA GpuTargetConfigProto (text) of the GPU to compile for')
_VARIANTS = flags.DEFINE_list('variants', ['scene', 'masked', 'bare'],
                              'benchmark_substep variants to compile')
_SUBSTEPS = flags.DEFINE_integer(
  'substeps', 8, 'substeps of the compiled frame (the scan trip count)')
_TARGETS = flags.DEFINE_list(
  'targets', ['mpm'], 'what to compile: mpm (a frame of the scene, per '
  'variant), render (the Pallas compositor, forward and gradient), '
  'simulate (the whole differentiable simulate of the scene and its '
  'gradient)')
_FRAMES = flags.DEFINE_integer('frames', 2, 'simulate: frames')
_KERNEL = flags.DEFINE_enum(
  'constitutive_kernel', 'auto', ['auto', 'jax', 'pallas'],
  'mpm, simulate: SimConfig.constitutive_kernel (auto: the stress update '
  'as one Pallas kernel on CUDA; jax: XLA\'s fusion)')
_RENDER_SIZE = flags.DEFINE_integer('render_size', 1024,
                                    'render: image edge [pixels]')
_RENDER_SLOTS = flags.DEFINE_integer(
  'render_slots', 800_000, 'render: (Gaussian, tile) intersection slots')
_RENDER_SUBTILE = flags.DEFINE_integer('render_subtile', 8,
                                      'render: RenderConfig.subtile_size')
_RENDER_BLOCK = flags.DEFINE_integer(
  'render_block', None, 'render: RenderConfig.pallas_block (None: its default)')
_RENDER_WARPS = flags.DEFINE_integer('render_warps', None,
                                    'render: RenderConfig.pallas_num_warps')
_OUT = cli.define_out(None, 'JSON file for the counts')

class GpuCompileError(PhysSplatError, RuntimeError):
  """No CUDA compiler to compile for a GPU without one."""


def gpu_device(spec_path: str):
  """A compile-only device for the GPU described by ``spec_path``."""
  from jax.experimental import topologies  # noqa: PLC0415

  try:
    spec = pathlib.Path(spec_path).read_text()
  except OSError as e:
    raise GpuCompileError(f'--spec: cannot read {spec_path}: {e}') from e
  try:
    topo = topologies.get_topology_desc(
      platform='cuda', topology_name='', target_config=spec,
      topology='1x1x1')
  except (NotImplementedError, RuntimeError, ValueError) as e:
    raise GpuCompileError(
      'compiling for a GPU without one needs a CUDA build of jaxlib: '
      "pip install 'jax[cuda13]' (no GPU needed), then run with "
      f'JAX_PLATFORMS=cpu ({type(e).__name__}: {e})') from e
  return topo.devices[0]


def _abstract(tree, sharding):
  return jax.tree.map(
    lambda a: jax.ShapeDtypeStruct(jnp.shape(a), jnp.result_type(a),
                                   sharding=sharding), tree)


def compile_render(sharding, size: int, slots: int,
                   config: RenderConfig) -> list[dict]:
  """Compiles the Pallas compositor (the Triton kernels of
  ``render/pallas_raster.py``), forward and gradient, for a ``size``^2
  image with ``slots`` sorted (Gaussian, sub-tile) slots."""
  tiles = -(-size // config.tile_size)
  sub = (config.tile_size // config.resolved_subtile) ** 2
  num_gaussians = slots // 8
  feat = jax.ShapeDtypeStruct((num_gaussians, 10), jnp.float32,
                              sharding=sharding)
  gid = jax.ShapeDtypeStruct((slots,), jnp.int32, sharding=sharding)
  ranges = jax.ShapeDtypeStruct((tiles * tiles * sub + 1,), jnp.int32,
                                sharding=sharding)

  def forward(feat, gid, ranges):
    return pallas_raster.rasterize(feat, gid, ranges, tiles, tiles, config)

  def loss(feat, gid, ranges):
    log_t, acc = forward(feat, gid, ranges)
    return jnp.sum(acc) + jnp.sum(log_t)

  rows = []
  for name, fn in (('render forward', forward),
                   ('render gradient', jax.grad(loss))):
    t = time.perf_counter()
    text = jax.jit(fn).lower(feat, gid, ranges).compile().as_text()
    comps, entry = hlo.parse_hlo(text)
    k = hlo.kernels(comps, entry)
    rows.append(dict(variant=name, compile_s=round(time.perf_counter() - t, 1),
                     kernels=sum(k.values()), by_kind=dict(sorted(k.items())),
                     triton_kernels=text.count('__gpu$xla.gpu.triton')))
  return rows


def compile_simulate(sharding, scene_name: str, frames: int) -> list[dict]:
  """Compiles the whole differentiable ``simulate`` (MPDP field, MPM,
  deformation, the render-only rasterizer) of a scene with ``--preset``'s
  settings for ``frames`` frames, and the gradient of a loss on the final
  Gaussian means (rendering off) with respect to every parameter."""
  config, prepared, params = substep_lib.demo_scene(scene_name, _PRESET.value)
  config = dataclasses.replace(config, num_frames=frames,
                               constitutive_kernel=_KERNEL.value)
  sim = config.simulate
  nograd = dataclasses.replace(sim, render='none')

  def forward(p, s):
    return pl.simulate(p, s, sim)

  def loss(p, s):
    return pl.simulate(p, s, nograd).means[-1, :, 2].mean()

  rows = []
  for name, fn in (('simulate forward', forward),
                   ('simulate gradient', jax.grad(loss))):
    t = time.perf_counter()
    text = jax.jit(fn).lower(_abstract(params, sharding),
                             _abstract(prepared, sharding)).compile().as_text()
    comps, entry = hlo.parse_hlo(text)
    k = hlo.kernels(comps, entry)
    rows.append(dict(variant=name, compile_s=round(time.perf_counter() - t, 1),
                     kernels=sum(k.values()), by_kind=dict(sorted(k.items()))))
  return rows


def main(argv):
  del argv
  cli.check_output_file('out', _OUT.value)  # before minutes of compiling
  # Lowered for a GPU this host need not have: traces keep every
  # platform's form (physsplat_jax.platforms).
  with platforms.every_platform():
    _compile_targets()


def _compile_targets():
  dump_dir = ptxas = None
  if {'render', 'mpm'} & set(_TARGETS.value):
    # ptxas reads the PTX that XLA dumps; the flag must be set before XLA
    # reads its flags (the first compile).
    ptxas = ptxas_lib.find_ptxas()
    if ptxas is None:
      logging.warning('no ptxas (nvidia-cuda-nvcc wheel or PATH): Pallas '
                      'kernels compiled without a register report')
    else:
      dump_dir = tempfile.mkdtemp(prefix='gpu_kernels_')
      os.environ['XLA_FLAGS'] += f' --xla_dump_to={dump_dir}'
  device = gpu_device(_SPEC.value)
  sharding = jax.sharding.SingleDeviceSharding(device)
  rows = []
  if 'render' in _TARGETS.value:
    config = RenderConfig(
      backend='pallas', subtile_size=_RENDER_SUBTILE.value,
      pallas_num_warps=_RENDER_WARPS.value)
    if _RENDER_BLOCK.value is not None:
      config = dataclasses.replace(config, pallas_block=_RENDER_BLOCK.value)
    for row in compile_render(sharding, _RENDER_SIZE.value,
                              _RENDER_SLOTS.value, config):
      rows.append(row)
      print(f"{row['variant']:18s} compiled in {row['compile_s']} s: "
            f"{row['kernels']} kernels in all, "
            f"{row['triton_kernels']} Triton (Pallas)")
    if dump_dir is not None:
      limits = ptxas_lib.spec_limits(pathlib.Path(_SPEC.value).read_text())
      res = ptxas_lib.kernel_resources(
        dump_dir, ('splat_forward', 'splat_backward'), limits, ptxas)
      block, fw, bw = config.resolved_pallas()
      rows.append(dict(variant='render kernels (ptxas)',
                       subtile=config.resolved_subtile, block=block,
                       forward_warps=fw, backward_warps=bw, kernels=res))
      for name, r in res.items():
        print(f"{name:18s} {r['registers']} registers, {r['spill_bytes']} B "
              f"spilled, {r['threads']} threads, {r['shared_bytes']} B "
              f"shared: {r['warps_per_sm']} warps/SM; "
              f"{r['ptx_instructions']} PTX instructions")
  if 'simulate' in _TARGETS.value:
    for row in compile_simulate(sharding, _SCENE.value, _FRAMES.value):
      rows.append(row)
      print(f"{row['variant']:18s} compiled in {row['compile_s']} s")
  info = dict(spec=os.path.basename(_SPEC.value), jax_version=jax.__version__)
  if 'mpm' not in _TARGETS.value:
    if dump_dir is not None:
      shutil.rmtree(dump_dir, ignore_errors=True)
    cli.write_json(_OUT.value, dict(info, rows=rows))
    return
  prepared, state, mats, forces, sim_config = (
    substep_lib.demo_scene_state(_SCENE.value, _PRESET.value))
  sim_config = dataclasses.replace(sim_config,
                                   substeps_per_frame=_SUBSTEPS.value)
  for name in _VARIANTS.value:
    s, m, f, c = substep_lib.variant(name, state, mats, forces, sim_config)
    c = dataclasses.replace(c, constitutive_kernel=_KERNEL.value)
    args = _abstract((s, m, f), sharding)
    t = time.perf_counter()
    compiled = jax.jit(substep_lib.make_frame(name, c)).lower(*args).compile()
    seconds = time.perf_counter() - t
    row = dict(variant=name, compile_s=round(seconds, 1),
               **hlo.substep_kernels(compiled.as_text(), _SUBSTEPS.value))
    rows.append(row)
    logging.info('%s', row)
    print(f"{name:18s} {row['kernels']:4d} kernels/substep  "
          f"({', '.join(f'{k} {v}' for k, v in row['by_kind'].items())}), "
          f"compiled in {row['compile_s']} s")
  if dump_dir is not None:
    # The constitutive update's Pallas kernel (mpm/pallas_constitutive.py):
    # registers and spills of the last variant compiled with it.
    limits = ptxas_lib.spec_limits(pathlib.Path(_SPEC.value).read_text())
    res = ptxas_lib.kernel_resources(dump_dir, ('constitutive_update',),
                                     limits, ptxas)
    for name, r in res.items():
      rows.append(dict(variant=f'{name} (ptxas)', **r))
      print(f"{name:18s} {r['registers']} registers, {r['spill_bytes']} B "
            f"spilled, {r['threads']} threads: {r['warps_per_sm']} warps/SM; "
            f"{r['ptx_instructions']} PTX instructions")
    shutil.rmtree(dump_dir, ignore_errors=True)
  cli.write_json(_OUT.value, dict(
    info, scene=_SCENE.value, particles=prepared.num_particles,
    models=sim_config.models, rows=rows))


if __name__ == '__main__':
  cli.run(main, cache_default='off')
