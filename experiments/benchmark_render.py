"""Renderer benchmark: compile and steady time per frame, CPU or GPU.

  python -m experiments.benchmark_render --num=100000,1000000 --size=512
  python -m experiments.benchmark_render --scene=ficus --width=512 \\
      --height=384 --repeats=10

Scenes: Gaussians on a sphere shell (radius 1, opacity 0.95, scales ~ 1/sqrt(K)
so the surface stays closed) seen from distance 3, as in REFERENCE 5.3; or a
scene (--scene: a built-in name or a PLY path, seen from its first camera).
The capacity is fitted once (as for a video), compile time is measured apart
(``lower().compile()``), then ``--repeats`` runs are timed with
``block_until_ready``; the minimum wall time and process CPU time are
reported (CPU time is what survives a busy shared machine). ``--baseline``
also times, in the same process, the gsplat-style binning (16-px tiles,
3-sigma rectangles, no sub-tiles) with the same compositor, and reports the
ratio; ``--compare`` the cumsum prefix; ``--grad`` a reverse-mode gradient
through the differentiable path.

GPU path: ``--backend`` picks the compositor of the main run (``auto``:
Pallas on a GPU, JAX elsewhere); ``--pallas`` also times the Pallas
compositor (forward, and the gradient with ``--grad``) beside it and reports
its max abs difference and PSNR to the main run's image, and the largest
difference of its gradients (means, SH) relative to the main run's (with
``--backend=jax`` this checks the compiled kernels against the JAX path;
off a GPU it needs ``--interpret``: slow, a correctness run only). If
``gsplat`` imports and CUDA is available, gsplat 1.5.3's
``rasterization`` is timed in the same process on the same Gaussians
and camera (quaternions wxyz, OpenCV world-to-camera viewmat, black
background), forward and (with ``--grad``) the gradient of the mean
image w.r.t. means and SH, with the PSNR of our image against gsplat's::

  python -m experiments.benchmark_render --num=100000,1000000 --size=1024 \\
      --grad --pallas --repeats=10

``--video_frames=F`` also renders a video: F frames with the camera
turning once about the scene's up axis through its centre, each through
the host path of ``pipeline.run`` (``render_image_async`` with the fitted
config, one frame in flight while the previous one is fetched, clipped and
converted to uint8), after one warm-up frame; ``video_s`` is the wall time
of the F frames. With gsplat, ``gsplat_video_s`` is the same loop through
``rasterization`` (image clamped, converted to uint8 on the device and
copied to the host)::

  python -m experiments.benchmark_render --num=100000 --width=800 \\
      --height=800 --video_frames=150
"""

from __future__ import annotations

import dataclasses
import json
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import flags

from experiments.lib import cli
from physsplat_jax import cameras
from physsplat_jax import gaussians as gs
from physsplat_jax.io import video as video_lib
from physsplat_jax.pipeline import capture
from physsplat_jax.render import images
from physsplat_jax.render import raster
from physsplat_jax.render import views
from physsplat_jax.types import Gaussians
from physsplat_jax.types import make_camera

_NUM = flags.DEFINE_list('num', ['100000'], 'Gaussian counts (sphere).')
_SIZE = flags.DEFINE_integer('size', 512, 'Sphere image width and height.',
                             lower_bound=1)
_WIDTH = flags.DEFINE_integer('width', None,
                              'Image width [px] (sphere: instead of size).',
                              lower_bound=1)
_HEIGHT = flags.DEFINE_integer('height', None,
                               'Image height [px] (sphere: instead of size).',
                               lower_bound=1)
_REPEATS = flags.DEFINE_integer('repeats', 3, 'Timed runs per setting.',
                                lower_bound=1)
_SCENE = flags.DEFINE_string('scene', None, 'Built-in scene or PLY instead.')
_BASELINE = flags.DEFINE_bool('baseline', False,
                              'Also time 16-px tiles with 3-sigma rects.')
_COMPARE = flags.DEFINE_bool('compare', False, 'Also time prefix=cumsum.')
_GRAD = flags.DEFINE_bool('grad', False, 'Also time a gradient.')
_CHUNK = flags.DEFINE_integer('chunk', 64, 'RenderConfig.chunk_size.')
_SUBTILE = flags.DEFINE_integer('subtile', 8, 'RenderConfig.subtile_size.')
_BATCH = flags.DEFINE_integer('tile_batch', 1, 'RenderConfig.tile_batch.')
_BACKEND = flags.DEFINE_enum('backend', 'auto', ['auto', 'jax', 'pallas'],
                             'RenderConfig.backend of the main run.')
_PALLAS = flags.DEFINE_bool('pallas', False,
                            'Also time backend=pallas (and its gradient).')
_INTERPRET = flags.DEFINE_bool('interpret', False,
                               'Pallas interpret mode (CPU, slow).')
_BLOCK = flags.DEFINE_integer('pallas_block', None,
                              'RenderConfig.pallas_block (None: its default).')
_WARPS = flags.DEFINE_integer('num_warps', None,
                              'RenderConfig.pallas_num_warps.')
_GSPLAT = flags.DEFINE_bool('gsplat', True,
                            'Also time gsplat when importable with CUDA.')
_VIDEO = flags.DEFINE_integer(
  'video_frames', 0, 'Also time a video of this many orbiting frames.',
  lower_bound=0)
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


def sphere_camera(size: int, width: int | None = None,
                  height: int | None = None):
  """The sphere's camera, ``size`` square unless ``width``/``height``."""
  w, h = width or size, height or size
  vm = cameras.look_at(np.array([0.0, -3.0, 0.5]), np.zeros(3))
  f = cameras.focal_from_fov(45.0, w)
  return make_camera(vm, f, f, w, h)


def _time(fn, *args, repeats):
  t0 = time.perf_counter()
  compiled = fn.lower(*args).compile()
  compile_s = time.perf_counter() - t0
  wall, cpu = [], []
  out = None
  for _ in range(repeats):
    t0, c0 = time.perf_counter(), time.process_time()
    out = jax.block_until_ready(compiled(*args))
    wall.append(time.perf_counter() - t0)
    cpu.append(time.process_time() - c0)
  return compile_s, min(wall), min(cpu), out


def _render_fn(config):
  return jax.jit(lambda g, cam: raster.render(g, cam, config=config))


def _grad_fn(g, cam, config):
  def loss(means, sh):
    o = raster.render_differentiable(g.replace(means=means, sh=sh), cam,
                                     config=config)
    return jnp.mean(o.image)

  return jax.jit(jax.grad(loss, argnums=(0, 1)))


def _psnr(a, b) -> float:
  mse = float(np.mean((np.asarray(a, np.float64)
                       - np.asarray(b, np.float64)) ** 2))
  return float('inf') if mse == 0 else -10.0 * np.log10(mse)


def _gsplat(g: Gaussians, cam):
  """gsplat's ``rasterization`` on our scene: ``(render, means, sh, torch,
  version)``, ``render(means, sh, viewmat=None)`` giving the (H, W, 3)
  image; None without gsplat or CUDA.

  gsplat takes wxyz quaternions, linear scales, opacities in [0, 1], SH
  (K, B, 3) and an OpenCV world-to-camera viewmat, as we do.
  """
  try:
    import gsplat
    import torch
  except ImportError:
    return None
  if not torch.cuda.is_available():
    return None
  dev = torch.device('cuda')
  t = lambda x: torch.tensor(np.asarray(x, np.float32), device=dev)
  means, quats, sh = t(g.means), t(g.quats), t(g.sh)
  scales, opac = t(np.exp(np.asarray(g.log_scales))), t(g.opacities)
  viewmats, Ks = t(cam.viewmat)[None], t(cam.K)[None]
  degree = int(round(np.sqrt(g.sh.shape[1]))) - 1

  def render(m, c, viewmat=None):
    vm = viewmats if viewmat is None else t(viewmat)[None]
    img, _, _ = gsplat.rasterization(m, quats, scales, opac, c, vm, Ks,
                                     cam.width, cam.height,
                                     sh_degree=degree)
    return img[0]

  return render, means, sh, torch, gsplat.__version__


def bench_gsplat(g: Gaussians, cam, repeats: int, grad: bool,
                 image=None) -> dict:
  """Times gsplat's ``rasterization`` on the same scene (empty if absent).

  Returns ``gsplat_s``, ``gsplat_grad_s`` (gradient of the mean image
  w.r.t. means and SH) and ``gsplat_psnr_db`` (our ``image`` against
  gsplat's).
  """
  setup = _gsplat(g, cam)
  if setup is None:
    return {}
  run, means, sh, torch, version = setup

  def timed(fn):
    fn()
    torch.cuda.synchronize()
    best = float('inf')
    for _ in range(repeats):
      t0 = time.perf_counter()
      fn()
      torch.cuda.synchronize()
      best = min(best, time.perf_counter() - t0)
    return best

  res = {'gsplat_version': version}
  with torch.no_grad():
    res['gsplat_s'] = timed(lambda: run(means, sh))
    img = run(means, sh).cpu().numpy()
  if image is not None:
    res['gsplat_psnr_db'] = _psnr(image, img)
  if grad:
    m2 = means.clone().requires_grad_(True)
    s2 = sh.clone().requires_grad_(True)

    def step():
      loss = run(m2, s2).mean()
      torch.autograd.grad(loss, (m2, s2))

    res['gsplat_grad_s'] = timed(step)
  return res


def _orbit(g: Gaussians, up) -> capture.CameraOrbit:
  m = np.asarray(g.means)
  return capture.CameraOrbit(
    center=jnp.asarray(0.5 * (m.min(0) + m.max(0)), jnp.float32),
    axis=jnp.asarray(up, jnp.float32), degrees=jnp.asarray(360.0))


def bench_video(g: Gaussians, cam, config: raster.RenderConfig, frames: int,
                up, use_gsplat: bool = True) -> dict:
  """A video of ``frames`` orbiting frames, as ``pipeline.run`` renders."""
  orbit, base = _orbit(g, up), cam.unlabelled()
  cam_fn = jax.jit(capture.frame_camera)
  # Warm-up: compiles, and fits the capacity that the frames then reuse.
  t0 = time.perf_counter()
  warm = images.render_image_async(g, cam_fn(base, orbit, 0, frames),
                                   config=config, fetch=('image',), clip=True)
  warm.result()
  config = warm.config
  warm_s = time.perf_counter() - t0
  print(f'video: warm-up frame (compiles) {warm_s:.2f} s', flush=True)
  # As pipeline.run: only the image comes to the host, clipped on the
  # device. Where the host's time goes per frame: dispatching the camera
  # and the render, waiting for the device, fetching the image (and any
  # re-run of an overflowing frame), and the uint8 conversion the writers
  # do.
  parts = dict(dispatch=0.0, wait=0.0, fetch=0.0, convert=0.0)
  reruns = 0
  t0 = time.perf_counter()
  pending = None
  for f in range(frames + 1):
    nxt = None
    t1 = time.perf_counter()
    if f < frames:
      nxt = images.render_image_async(g, cam_fn(base, orbit, f, frames),
                                      config=config, fetch=('image',),
                                      clip=True)
    t2 = time.perf_counter()
    parts['dispatch'] += t2 - t1
    if pending is not None:
      pending.wait()
      t3 = time.perf_counter()
      out = pending.result()
      t4 = time.perf_counter()
      video_lib.to_uint8(out.image)
      parts['wait'] += t3 - t2
      parts['fetch'] += t4 - t3
      parts['convert'] += time.perf_counter() - t4
      config = pending.config
      reruns += pending.reruns
    pending = nxt
  res = {'video_frames': frames, 'video_s': time.perf_counter() - t0,
         'video_warmup_s': warm_s, 'video_reruns': reruns,
         **{f'video_{k}_ms': 1e3 * v / frames for k, v in parts.items()}}
  print(f'video: {frames} frames in {res["video_s"]:.2f} s; per frame '
        + ', '.join(f'{k} {1e3 * v / frames:.2f} ms' for k, v in
                    parts.items())
        + f'; {reruns} re-runs (overflow)', flush=True)
  res['video_frame_ms'] = 1e3 * res['video_s'] / frames
  if use_gsplat:
    viewmats = [np.asarray(cam_fn(base, orbit, f, frames).viewmat)
                for f in range(frames)]
    res.update(_gsplat_video(g, cam, viewmats))
  return res


def _gsplat_video(g: Gaussians, cam, viewmats) -> dict:
  """gsplat renders the same frames, each to uint8 on the host."""
  setup = _gsplat(g, cam)
  if setup is None:
    return {}
  run, means, sh, torch, _ = setup

  def frame(vm):
    with torch.no_grad():
      img = run(means, sh, vm)
      return (img.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()

  frame(viewmats[0])
  torch.cuda.synchronize()
  t0 = time.perf_counter()
  for vm in viewmats:
    frame(vm)
  return {'gsplat_video_s': time.perf_counter() - t0}


def bench(g: Gaussians, cam, config: raster.RenderConfig, repeats: int,
          baseline: bool = False, compare: bool = False,
          grad: bool = False, pallas: bool = False,
          interpret: bool = False, use_gsplat: bool = True) -> dict:
  """Times one scene and camera; returns a dict of results."""
  config = images.fit_render_config(g, cam, config, margin=1.1)
  res = {'num': int(g.num), 'width': cam.width, 'height': cam.height,
         'capacity': config.capacity, 'device': str(jax.devices()[0])}
  c, t, tc, out = _time(_render_fn(config), g, cam, repeats=repeats)
  res.update(compile_s=c, render_s=t, render_cpu_s=tc,
             intersections=int(out.num_intersections),
             max_tile=int(out.max_tile_count), overflow=bool(out.overflow))
  if baseline:
    base = dataclasses.replace(config, subtile_size=None, tight_bounds=False,
                               capacity=None, max_chunks=None)
    base = images.fit_render_config(g, cam, base, margin=1.1)
    c2, t2, tc2, out2 = _time(_render_fn(base), g, cam, repeats=repeats)
    res.update(baseline_render_s=t2, baseline_render_cpu_s=tc2,
               baseline_intersections=int(out2.num_intersections),
               speedup_vs_baseline=t2 / t,  # (on a GPU: CPU time idles)
               speedup_vs_baseline_cpu=tc2 / tc,
               baseline_max_abs_diff=float(
                 jnp.abs(out2.image - out.image).max()))
  if compare:
    cfg2 = dataclasses.replace(config, prefix='cumsum')
    c2, t2, tc2, out2 = _time(_render_fn(cfg2), g, cam, repeats=repeats)
    res.update(cumsum_render_s=t2, cumsum_render_cpu_s=tc2,
               speedup_vs_cumsum=t2 / t,
               speedup_vs_cumsum_cpu=tc2 / tc,
               cumsum_max_abs_diff=float(
                 jnp.abs(out2.image - out.image).max()))
  res['backend'] = config.resolved_backend()
  if grad:
    gfn = _grad_fn(g, cam, config)
    cg, tg, tgc, grads = _time(gfn, g.means, g.sh, repeats=repeats)
    res.update(grad_compile_s=cg, grad_s=tg, grad_cpu_s=tgc,
               max_chunks=config.max_chunks)
  if pallas:
    cfg_p = dataclasses.replace(config, backend='pallas',
                                interpret=interpret)
    cp, tp, tpc, out_p = _time(_render_fn(cfg_p), g, cam, repeats=repeats)
    res.update(pallas_compile_s=cp, pallas_render_s=tp,
               pallas_render_cpu_s=tpc,
               pallas_max_abs_diff=float(
                 jnp.abs(out_p.image - out.image).max()),
               pallas_psnr_db=_psnr(out_p.image, out.image))
    if grad:
      cg, tg, tgc, grads_p = _time(_grad_fn(g, cam, cfg_p), g.means, g.sh,
                                   repeats=repeats)
      res.update(pallas_grad_compile_s=cg, pallas_grad_s=tg,
                 pallas_grad_cpu_s=tgc)
      # The compiled kernels' gradients against the configured path's
      # (the JAX compositor with --backend=jax), relative to the largest.
      for name, a, b in zip(('means', 'sh'), grads, grads_p):
        res[f'pallas_grad_{name}_rel_diff'] = float(
          jnp.abs(a - b).max() / jnp.maximum(jnp.abs(a).max(), 1e-30))
  if use_gsplat:
    gres = bench_gsplat(g, cam, repeats, grad, image=out.image)
    res.update(gres)
    for ours in ('render_s', 'pallas_render_s'):
      if 'gsplat_s' in gres and ours in res:
        res[f'{ours}_over_gsplat'] = res[ours] / gres['gsplat_s']
    for ours in ('grad_s', 'pallas_grad_s'):
      if 'gsplat_grad_s' in gres and ours in res:
        res[f'{ours}_over_gsplat'] = res[ours] / gres['gsplat_grad_s']
  return res


def main(argv):
  del argv
  cli.check_output_file('out', _OUT.value)  # (else lost after the runs)
  print('devices', jax.devices())
  machine = cli.machine()
  config = raster.RenderConfig(chunk_size=_CHUNK.value,
                               subtile_size=_SUBTILE.value,
                               tile_batch=_BATCH.value,
                               backend=_BACKEND.value,
                               interpret=_INTERPRET.value,
                               pallas_num_warps=_WARPS.value)
  if _BLOCK.value is not None:
    config = dataclasses.replace(config, pallas_block=_BLOCK.value)
  runs = []
  if _SCENE.value:
    from physsplat_jax.scenes import load_scene

    scene = load_scene(_SCENE.value)
    cam = views.scene_camera(scene, None, _WIDTH.value, _HEIGHT.value)
    runs.append((scene.gaussians, cam))
    up = scene.up_vector
  else:
    cam = sphere_camera(_SIZE.value, _WIDTH.value, _HEIGHT.value)
    up = (0.0, 0.0, 1.0)
    runs = [(sphere_scene(n), cam)
            for n in cli.positive_ints('num', _NUM.value)]
  results = []
  for g, cam in runs:
    r = bench(g, cam, config, _REPEATS.value, _BASELINE.value,
              _COMPARE.value, _GRAD.value, _PALLAS.value, _INTERPRET.value,
              _GSPLAT.value)
    if _VIDEO.value > 0:
      print(json.dumps(r), flush=True)  # what is measured so far
      print(f'video: {_VIDEO.value} frames', flush=True)
      r.update(bench_video(g, cam, config, _VIDEO.value, up, _GSPLAT.value))
    r['machine'] = machine
    print(json.dumps(r))
    results.append(r)
  cli.write_json(_OUT.value, results)


if __name__ == '__main__':
  cli.run(main, cache_default='off')
