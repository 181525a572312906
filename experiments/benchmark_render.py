"""Renderer benchmark: compile and steady time per frame, CPU or GPU.

  python -m experiments.benchmark_render --num=100000,1000000 --size=512

Scenes: Gaussians on a sphere shell (radius 1, opacity 0.95, scales ~ 1/sqrt(K)
so the surface stays closed) seen from distance 3, as in REFERENCE 5.3; or a
PLY file (--scene). Compile time is measured apart (``lower().compile()``),
then ``--repeats`` runs are timed with ``block_until_ready``. ``--compare``
also times the cumsum-prefix variant in the same process (a ratio that holds
on a busy machine).
"""

from __future__ import annotations

import dataclasses
import json
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app
from absl import flags

from physsplat_jax import cameras
from physsplat_jax import gaussians as gs
from physsplat_jax.render import raster
from physsplat_jax.types import Gaussians
from physsplat_jax.types import make_camera

_NUM = flags.DEFINE_list('num', ['100000'], 'Gaussian counts.')
_SIZE = flags.DEFINE_integer('size', 512, 'Image width and height [px].')
_REPEATS = flags.DEFINE_integer('repeats', 3, 'Timed runs per setting.')
_SCENE = flags.DEFINE_string('scene', None, 'Optional PLY instead.')
_COMPARE = flags.DEFINE_bool('compare', False, 'Also time prefix=cumsum.')
_GRAD = flags.DEFINE_bool('grad', False, 'Also time a gradient.')
_CHUNK = flags.DEFINE_integer('chunk', 64, 'RenderConfig.chunk_size.')
_BATCH = flags.DEFINE_integer('tile_batch', 1, 'RenderConfig.tile_batch.')
_OUT = flags.DEFINE_string('out', None, 'Optional JSON results file.')


def sphere_scene(num: int, seed: int = 0) -> Gaussians:
  """``num`` Gaussians on the unit sphere with random colours."""
  rng = np.random.default_rng(seed)
  v = rng.normal(size=(num, 3))
  v /= np.linalg.norm(v, axis=1, keepdims=True)
  s = 2.0 / np.sqrt(num)
  q = rng.normal(size=(num, 4))
  rgb = rng.uniform(0.1, 0.9, size=(num, 3))
  return Gaussians(
    means=jnp.asarray(v, jnp.float32),
    log_scales=jnp.full((num, 3), np.log(s), jnp.float32),
    quats=jnp.asarray(q, jnp.float32),
    opacity_logits=jnp.full((num,), np.log(0.95 / 0.05), jnp.float32),
    sh=jnp.asarray(gs.rgb_to_sh_dc(rgb)[:, None, :], jnp.float32),
  )


def _time(fn, *args, repeats):
  t0 = time.perf_counter()
  compiled = fn.lower(*args).compile()
  compile_s = time.perf_counter() - t0
  times = []
  out = None
  for _ in range(repeats):
    t0 = time.perf_counter()
    out = jax.block_until_ready(compiled(*args))
    times.append(time.perf_counter() - t0)
  return compile_s, min(times), out


def bench(g: Gaussians, size: int, config: raster.RenderConfig, repeats: int,
          compare: bool, grad: bool) -> dict:
  """Times one scene; returns a dict of results."""
  vm = cameras.look_at(np.array([0.0, -3.0, 0.5]), np.zeros(3))
  f = cameras.focal_from_fov(45.0, size)
  cam = make_camera(vm, f, f, size, size)
  config = raster.fit_render_config(g, cam, config, margin=1.1)
  res = {'num': int(g.num), 'size': size, 'capacity': config.capacity,
         'device': str(jax.devices()[0])}

  def fwd(g, cam, cfg):
    return jax.jit(lambda g, cam: raster.render(g, cam, config=cfg))

  c, t, out = _time(fwd(g, cam, config), g, cam, repeats=repeats)
  res.update(compile_s=c, render_s=t,
             intersections=int(out.num_intersections),
             max_tile=int(out.max_tile_count), overflow=bool(out.overflow))
  if compare:
    cfg2 = dataclasses.replace(config, prefix='cumsum')
    c2, t2, out2 = _time(fwd(g, cam, cfg2), g, cam, repeats=repeats)
    res.update(cumsum_render_s=t2, cumsum_compile_s=c2,
               speedup_vs_cumsum=t2 / t,
               max_abs_diff=float(jnp.abs(out2.image - out.image).max()))
  if grad:
    def loss(means, sh):
      o = raster.render_differentiable(
        g.replace(means=means, sh=sh), cam, config=config)
      return jnp.mean(o.image)

    gfn = jax.jit(jax.grad(loss, argnums=(0, 1)))
    cg, tg, _ = _time(gfn, g.means, g.sh, repeats=repeats)
    res.update(grad_compile_s=cg, grad_s=tg)
  return res


def main(argv):
  del argv
  print('devices', jax.devices())
  config = raster.RenderConfig(chunk_size=_CHUNK.value,
                               tile_batch=_BATCH.value)
  results = []
  scenes = []
  if _SCENE.value:
    from physsplat_jax.io.ply import load_ply

    scenes.append(load_ply(_SCENE.value))
  else:
    scenes = [sphere_scene(int(n)) for n in _NUM.value]
  for g in scenes:
    r = bench(g, _SIZE.value, config, _REPEATS.value, _COMPARE.value,
              _GRAD.value)
    print(json.dumps(r))
    results.append(r)
  if _OUT.value:
    with open(_OUT.value, 'w') as f:
      json.dump(results, f, indent=1)


if __name__ == '__main__':
  app.run(main)
