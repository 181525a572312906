"""The host loop: simulate frame by frame and hand each frame to writers.

One jitted MPM frame per call (``mpm.run``: per-frame stability checks
that stop with the frame and the fix), then the Gaussians are deformed and
rendered (re-sizing the rasterizer's capacity on overflow, never dropping
Gaussians) and every frame goes to each writer
(:mod:`physsplat_jax.io.outputs`). It logs one progress line per frame and
times each stage.
"""

from __future__ import annotations

from concurrent import futures
import dataclasses
import os
import time
from typing import Callable, Sequence

import jax
import numpy as np
from absl import logging

from physsplat_jax import mpm
from physsplat_jax import program_store
from physsplat_jax.io import outputs as out_lib
from physsplat_jax.io import spz as spz_io
from physsplat_jax.pipeline import capture as capture_lib
from physsplat_jax.pipeline.config import PipelineConfig
from physsplat_jax.pipeline.config import RenderMode
from physsplat_jax.pipeline.config import SimulateConfig
from physsplat_jax.pipeline.config import as_simulate_config
from physsplat_jax.pipeline.prepare import Params
from physsplat_jax.pipeline.prepare import PreparedScene
from physsplat_jax.pipeline.simulation import assemble_scene
from physsplat_jax.pipeline.simulation import deformed_gaussians
from physsplat_jax.pipeline.simulation import initial_state
from physsplat_jax.pipeline.simulation import make_sim_config
from physsplat_jax.render import images
from physsplat_jax.types import Array


@dataclasses.dataclass
class RunOutput:
  """Result of :func:`run` (NumPy, scene coordinates).

  Attributes:
    gaussian_positions: (T+1, Ks, 3) float32 centres of the simulated
      Gaussians.
    sim_rows: (Ks,) their row numbers in ``scene.gaussians``.
    particle_positions: (T+1, N, 3) float32 driving particles.
    times: (T+1,) [s].
    files: what was written ('video', 'frames', 'ply', 'spz', ...) ->
      path.
    timings: seconds per stage ('compile', 'simulate', 'deform', 'render',
      'write', 'total'; with rendering also 'render.dispatch' (the
      camera and the render dispatched, with frame 0's count of
      intersections) and 'render.wait' and 'render.fetch', the parts
      collected after dispatch: the device finishing, the fetch of the
      image, clipped on the device, with any re-run).
    particle_substeps_per_s: MPM throughput over the run.
    render_stats: ``capacities``, the intersection capacities the frames
      were rendered with (one compiled render program each), and
      ``reruns``, renders re-run larger after an overflow; empty without
      rendering.
  """

  gaussian_positions: np.ndarray
  sim_rows: np.ndarray
  particle_positions: np.ndarray
  times: np.ndarray
  files: dict
  timings: dict
  particle_substeps_per_s: float
  render_stats: dict = dataclasses.field(default_factory=dict)


def default_writers(prepared: PreparedScene, out_dir: str, fps: float, *,
                    video: bool = True, png: bool = True, ply: bool = False,
                    render: bool = True, num_frames: int | None = None,
                    spz: bool = False) -> list[out_lib.FrameWriter]:
  """The standard outputs of a run in ``out_dir``.

  With ``num_frames``, a warning is logged when the folder's disk has less
  free space than the outputs will take (:func:`output_sizes`).

  Raises:
    OutputError: the folder cannot be written, or the frames are too large
      for the video encoder (before the simulation: the encoder failed at
      the end of the run).
  """
  out_lib.check_output_dir(out_dir)
  writers = []
  size = (prepared.camera.width, prepared.camera.height)
  if video and render and max(size) > out_lib.MAX_VIDEO_SIDE:
    raise out_lib.OutputError(
      f'frames of {size[0]} x {size[1]} pixels: the MP4 encoder (H.264) '
      f'takes at most {out_lib.MAX_VIDEO_SIDE} a side; give a smaller '
      'width and height, or no video (PNG frames only: video=False)')
  if num_frames is not None:
    out_lib.check_free_space(out_dir, output_sizes(
      prepared, num_frames, video=video and render, png=png and render,
      ply=ply, spz=spz))
  if video and render:
    writers.append(out_lib.VideoOutput(os.path.join(out_dir, 'video.mp4'),
                                       fps))
  if png and render:
    writers.append(out_lib.PngOutput(os.path.join(out_dir, 'frames')))
  for kind, on in ((out_lib.PlyOutput, ply), (out_lib.SpzOutput, spz)):
    if on:
      writers.append(kind(os.path.join(out_dir, kind.format),
                          prepared.gaussians))
  writers.append(out_lib.TrajectoryOutput(
    os.path.join(out_dir, 'trajectory.npz'), np.asarray(prepared.sim_rows)))
  return writers


# A .spz frame's size after gzip over its size before, at the frames'
# gzip level 1 (io.outputs.SpzOutput): measured 0.75 on the donut (50245
# Gaussians, SH 0; 0.73 at level 6) and 0.49 on tests/data/udon_crop.ply
# at SH 3; rounded up, as an estimate of free space should be.
SPZ_GZIP_RATIO = 0.8
# Float32 properties a Gaussian of a PLY frame has: x y z, nx ny nz, 3 DC
# and 45 higher SH coefficients, opacity, 3 scales, 4 quaternion entries.
# (The estimate used to count the scene's own SH degree and no normals:
# 56 bytes a Gaussian for the donut, whose frames take 248.)
PLY_FRAME_PROPERTIES = 62


def output_sizes(prepared: PreparedScene, num_frames: int, *,
                 video: bool = True, png: bool = True,
                 ply: bool = False, spz: bool = False) -> dict[str, float]:
  """Bytes the default outputs of ``num_frames`` frames take, estimated:
  the trajectory exactly (float32 centres of the simulated Gaussians and
  the driving particles, their rows), a PNG frame at 0.6 byte per pixel
  and an H.264 frame at 0.02 (the tabletop's demo: 0.61 and 0.011), a PLY
  frame at the INRIA layout's 62 float32 properties a Gaussian (SH degree
  3 and normals, as :class:`~physsplat_jax.io.outputs.PlyOutput` writes
  it, whatever the scene's degree) and a .spz frame at
  ``SPZ_GZIP_RATIO`` of its bytes before gzip (20 a Gaussian, 3 per SH
  coefficient of degree >= 1)."""
  T = int(num_frames) + 1
  px = prepared.camera.width * prepared.camera.height
  g = prepared.gaussians
  ks = int(np.shape(prepared.sim_rows)[0])
  return {
    'trajectory': T * 12.0 * (ks + prepared.num_particles) + 8.0 * ks,
    'frames': T * 0.6 * px if png else 0.0,
    'video': T * 0.02 * px if video else 0.0,
    'ply': T * 4.0 * PLY_FRAME_PROPERTIES * g.num if ply else 0.0,
    'spz': (T * SPZ_GZIP_RATIO * spz_io.payload_bytes(g.num, g.sh_degree)
            if spz else 0.0)}


# The per-frame host programs, compiled once per process and shape (not per
# run): the frame index, frame count and driver-F switch are their only
# non-array inputs. Stored traced with a cache folder (program_store), so
# that a later process neither traces nor lowers them.
@program_store.stored_jit(name='host_deform', static_argnames=('use_driver_F',))
def _deform_jit(view, x, F, use_driver_F: bool):
  return deformed_gaussians(view, SimulateConfig(use_driver_F=use_driver_F),
                            x, F)


def _to_scene(fr, x):
  return fr.to_scene(x)


_assemble_jit = program_store.stored_jit(assemble_scene, name='host_assemble')
_to_scene_jit = program_store.stored_jit(_to_scene, name='host_to_scene')
_camera_jit = program_store.stored_jit(capture_lib.frame_camera,
                                       name='host_camera')


@program_store.stored_jit(name='initial_state', static_argnames=('config',))
def _initial_state_jit(params, prepared, config, field):
  return initial_state(params, prepared, config, field)[:3]


@dataclasses.dataclass
class _Pending:
  """One frame's device work, dispatched and not yet waited for."""

  index: int
  time: float
  x: Array
  means: Array
  particles: Array
  gaussians: object = None
  covariances: Array | None = None
  rotations: Array | None = None
  render: images.PendingRender | None = None


class _FrameMaker:
  """Deforms and renders frames (compiled once), in two halves.

  :meth:`dispatch` queues a frame's deformation and render on the device
  and returns at once; :meth:`finish` waits for them and builds the
  :class:`~physsplat_jax.io.outputs.Frame`. ``run`` finishes frame ``f``
  after dispatching frame ``f + 1``'s work, so the host's per-frame work
  overlaps the device's.
  """

  def __init__(self, prepared: PreparedScene, config: SimulateConfig,
               need_all: bool, timings: dict, device=None):
    self.prepared = prepared
    self.config = config
    self.render = config.render is not RenderMode.NONE
    self.need_all = need_all or self.render
    self.rcfg = config.render_config
    self.timings = timings
    # What the per-frame helpers see of the scene: no static spec (time
    # step, particle split, colliders) and no camera (image size), so that
    # none of these recompiles them.
    self.view = prepared.replace(spec=None, camera=None)
    self.camera = prepared.camera.unlabelled()
    self.orbit, self.background = prepared.orbit, prepared.background
    # A device of its own for deforming and rendering (``_frame_device``):
    # the scene's arrays are copied there once, each frame's x and F per
    # frame.
    self.device = device
    if device is not None:
      self.view, self.camera, self.orbit, self.background = jax.device_put(
        (self.view, self.camera, self.orbit, self.background), device)
    self.capacities: list[int] = []  # in order of first use
    self.reruns = 0

  def dispatch(self, f: int, t: float, state) -> _Pending:
    t1 = time.perf_counter()
    if self.device is not None:
      state = state.replace(x=jax.device_put(state.x, self.device),
                            F=jax.device_put(state.F, self.device))
    means, covs, rots = _deform_jit(self.view, state.x, state.F,
                                    use_driver_F=self.config.use_driver_F)
    # What finish() fetches is copied to the host as soon as it is ready.
    p = _Pending(index=f, time=t, x=state.x, means=means,
                 particles=_to_scene_jit(self.view.frame, state.x))
    images.start_host_copies((p.x, p.means, p.particles))
    if self.need_all:
      p.gaussians, p.covariances, p.rotations = _assemble_jit(
        self.view, means, covs, rots)
    t2 = time.perf_counter()
    self.timings['deform'] += t2 - t1
    if self.render:
      camera = _camera_jit(self.camera, self.orbit, f,
                           self.config.num_frames)
      # Only the image comes to the host, clipped on the device.
      p.render = images.render_image_async(
        p.gaussians, camera, background=self.background,
        covariances=p.covariances, view_rotations=p.rotations,
        config=self.rcfg, fetch=('image',), clip=True,
        headroom=VIDEO_HEADROOM)
      # The counted capacity (first frame) serves the next frames too. A
      # capacity grown by frame f's re-run reaches frame f + 2 (frame f + 1
      # is dispatched before f is collected): f + 1 may re-run as well.
      self._keep_larger(p.render.config, p.gaussians.num)
      dt = time.perf_counter() - t2
      self.timings['render'] += dt
      self.timings['render.dispatch'] += dt
    return p

  def finish(self, p: _Pending) -> out_lib.Frame:
    t1 = time.perf_counter()
    frame = out_lib.Frame(
      index=p.index, time=p.time, positions=np.asarray(p.means, np.float32),
      particles=np.asarray(p.particles), gaussians=p.gaussians,
      covariances=p.covariances, rotations=p.rotations)
    t2 = time.perf_counter()
    self.timings['deform'] += t2 - t1
    if p.render is not None:
      # Sub-stages: the device finishing the render, the fetch of the
      # clipped image (and any re-run).
      p.render.wait()
      t3 = time.perf_counter()
      self.timings['render.wait'] += t3 - t2
      out = p.render.result()
      t4 = time.perf_counter()
      self.timings['render.fetch'] += t4 - t3
      self.reruns += p.render.reruns
      cap = p.render.config.resolved_capacity(p.gaussians.num)
      if cap not in self.capacities:
        self.capacities.append(cap)
      self._keep_larger(p.render.config, p.gaussians.num)
      if p.index == 0 and int(out.num_visible) == 0:
        logging.warning(
          'frame 0: the camera sees none of the %d Gaussians (all behind it, '
          'outside its view or its near/far range): the video will show only '
          'the background; pick another camera (camera_index, -1 fits one to '
          'the scene) or check the scene\'s up axis.', p.gaussians.num)
      frame.image = out.image  # clipped to [0, 1] on the device
      self.timings['render'] += time.perf_counter() - t2
    return frame

  def _keep_larger(self, cfg, k: int) -> None:
    """Keeps a capacity that a frame needed (counted or grown): the first
    one counted even when it is below the automatic size, so that the later
    frames neither count again (a wait for the device each) nor compile a
    renderer for each count's size; a frame that outgrows it re-runs."""
    if cfg.capacity is not None and (
        self.rcfg.capacity is None
        or cfg.resolved_capacity(k) > self.rcfg.resolved_capacity(k)):
      self.rcfg = dataclasses.replace(self.rcfg, capacity=cfg.capacity)


# Capacity for a video's frames, over the intersections counted at frame 0
# (or at an overflow): the objects move, and a frame that outgrows the
# capacity re-runs and compiles a renderer of the next size. The donut at
# paper scale grew by 10-23 % after frame 0 (two re-runs with 1.1); the
# larger sort costs 7 % of a 480x360 tabletop render on the 2-core CPU.
VIDEO_HEADROOM = 1.5


def _frame_device(choice, state, pipelined: bool):
  """Where the per-frame deformation and render run (None: with the
  simulation).

  'auto' picks a second CPU device when the simulation runs pipelined on a
  CPU device and the process has another one (``jax_num_cpu_devices``):
  XLA runs one device's programs one after another, so on the simulation's
  own device frame ``f``'s render waited for frame ``f + 1``'s simulation;
  on another it runs beside it. On a GPU the render stays on the GPU.
  """
  if choice != 'auto':
    return choice
  if not pipelined:
    return None
  sim = next(iter(state.x.devices()))
  if sim.platform != 'cpu':
    return None
  others = [d for d in jax.local_devices(backend='cpu') if d != sim]
  return others[0] if others else None


class _WallWatch:
  """Warns once when particles press on the grid's walls: the domain is too
  small for the motion and the walls, not the physics, stop them."""

  _NAMES = ('-x', '+x', '-y', '+y', 'floor', 'ceiling')

  def __init__(self, spec):
    self.lo = np.asarray(spec.grid_lower) + 3.5 * spec.dx
    self.hi = np.asarray(spec.grid_lower) + spec.grid_size - 3.5 * spec.dx
    self.warned = False

  def check(self, f: int, x) -> None:
    if self.warned:
      return
    x = np.asarray(x)
    # (N, 3, 2) -> per wall: -x, +x, -y, +y, floor, ceiling.
    hit = np.stack([x < self.lo, x > self.hi], -1).reshape(len(x), 6).any(0)
    if hit.any():
      self.warned = True
      which = [n for n, h in zip(self._NAMES, hit) if h]
      logging.warning(
        'frame %d: particles press on the domain walls (%s): the grid is too '
        'small for this motion, so the walls stop them; raise margin (or '
        'lower the velocities) so the grid holds the whole motion.', f,
        ', '.join(which))


def _pipeline_fix(e, prepared):
  """The solver's error with the fix in the pipeline's terms (the solver
  speaks of dt and damping; a pipeline user sets config fields)."""
  head = mpm.split_fix(e)
  if head is None:
    return e
  n = prepared.spec.substeps_per_frame
  return mpm.SimulationError(
    f'{head}Give more substeps per frame (now {n}: substeps_per_frame='
    f'{2 * n}, or a lower cfl with the automatic choice), lower the '
    "stiffest object's E (--material_override=NAME={\"E\": ...}), lower "
    'the initial velocities or forces, or raise margin if it was thrown '
    'out of the grid.', e.frame, e.reason)


@out_lib.holds_output_dir()
def run(
  params: Params,
  prepared: PreparedScene,
  config: SimulateConfig | PipelineConfig,
  *,
  out_dir: str | None = None,
  video: bool = True,
  png: bool = True,
  ply: bool = False,
  spz: bool = False,
  writers: Sequence[out_lib.FrameWriter] | None = None,
  field: Array | None = None,
  on_frame: Callable | None = None,
  fps: float | None = None,
  pipelined: bool = True,
  render_device='auto',
) -> RunOutput:
  """Host loop: simulate frame by frame, streaming frames to writers.

  Pipelined (the default), the device is never left waiting for the host:
  frame ``f + 1`` is simulated while frame ``f`` is deformed and rendered,
  and frame ``f - 1`` is fetched, checked and handed to the writers
  meanwhile; before the loop, the deformation and renderer compile on a
  second thread while the MPM frame compiles. The outputs are the same
  either way.

  Args:
    params: :class:`Params`.
    prepared: from :func:`prepare_scene`.
    config: the :class:`SimulateConfig` (or :class:`PipelineConfig`).
    out_dir: folder for the default writers (``video.mp4``, ``frames/``,
      ``trajectory.npz``, optional ``ply/`` and ``spz/``); None writes
      nothing.
    video, png, ply, spz: which default outputs to write (``ply``:
      ``ply/frame_%04d.ply``, ``spz``: ``spz/frame_%04d.spz``, every
      Gaussian deformed).
    writers: writers to use instead of (``out_dir`` None) or beside the
      defaults (:mod:`physsplat_jax.io.outputs`).
    field: optional (N, 3) material field (e.g. ``prepared.field``, the
      field evaluated at preparation) instead of evaluating MPDP again.
    on_frame: optional ``callback(frame, means, image)`` (scene
      coordinates; image None when nothing is rendered).
    fps: video frame rate; default the prepared scene's frame rate.
    pipelined: overlap the host's per-frame work with the device's. Then
      ``timings`` are the time the host *waited* for each stage (frame
      0's deform and render include compiling them, concurrently with
      ``compile``) and
      ``particle_substeps_per_s`` is over the simulation's waits; False
      runs the stages one after the other, for exact per-stage times.
      Frame 0 is dispatched from a worker thread: JAX settings made by a
      context manager around ``run`` (thread-local, e.g. ``jax.
      default_device``) do not reach it; set them globally, or pass False.
    render_device: where the frames are deformed and rendered: 'auto' (a
      second CPU device when the simulation runs pipelined on a CPU and
      the process has one, e.g. ``jax.config.update('jax_num_cpu_devices',
      2)`` before JAX starts, as ``experiments.demo`` and ``simulate`` do:
      the render then runs beside the next frame's simulation instead of
      after it), None (the simulation's device), or a ``jax.Device``.
      The outputs are the same.

  Returns:
    :class:`RunOutput`.

  Raises:
    physsplat_jax.mpm.SimulationError: the simulation blew up (names the
      frame and the fix); every writer is closed first, so what was
      written so far is complete.
  """
  config = as_simulate_config(config)
  t_start = time.perf_counter()
  timings = dict(compile=0.0, simulate=0.0, deform=0.0, render=0.0,
                 write=0.0)
  if config.render is not RenderMode.NONE:
    timings.update({'render.dispatch': 0.0, 'render.wait': 0.0,
                    'render.fetch': 0.0})
  fps = fps or 1.0 / prepared.spec.frame_dt
  writers = list(writers or ())
  if out_dir is not None:
    writers = default_writers(
      prepared, out_dir, fps, video=video, png=png, ply=ply, spz=spz,
      render=config.render is not RenderMode.NONE,
      num_frames=config.num_frames) + writers
  t0 = time.perf_counter()
  sim_config = make_sim_config(prepared.spec, config, prepared.x0.dtype)
  # Keyed on the config without its frame count and on the scene without
  # its camera (initial_state reads neither): a run of another length or
  # image size reuses this program too.
  state, materials, forces = _initial_state_jit(
    params, prepared.replace(camera=None),
    dataclasses.replace(config, num_frames=1), field)
  timings['compile'] += time.perf_counter() - t0
  maker = _FrameMaker(prepared, config, ply or spz, timings,
                      _frame_device(render_device, state, pipelined))
  positions, particles = [], []
  num = config.num_frames

  walls = _WallWatch(prepared.spec)

  # Files are encoded on writer threads while the next frame computes;
  # 'write' is the time the loop waited for them.
  sink = out_lib.BackgroundWriters(writers)

  def consume(p: _Pending) -> None:
    t1 = time.perf_counter()
    frame = maker.finish(p)
    walls.check(p.index, p.x)
    t3 = time.perf_counter()
    sink.write(frame)
    timings['write'] += time.perf_counter() - t3
    positions.append(frame.positions)
    particles.append(frame.particles)
    if on_frame is not None:
      on_frame(p.index, frame.positions, frame.image)
    if p.index > 0:
      logging.info('frame %d/%d: deform+render+write %.2f s on the host%s',
                   p.index, num, time.perf_counter() - t1,
                   ' (overlapping the next frame)' if pipelined else '')

  pending = first = None

  def flush() -> None:  # writes the frame still in flight, if any
    nonlocal pending
    if pending is not None:
      q, pending = pending, None
      consume(q)

  try:
    with futures.ThreadPoolExecutor(1) as pool:
      if pipelined:
        # Frame 0's deformation and render need only the initial state:
        # their programs compile on a second thread while this one compiles
        # the MPM frame (XLA releases the GIL while it compiles).
        first = pool.submit(maker.dispatch, 0, 0.0, state)
      loop = mpm.FrameLoop(state, materials, forces, sim_config, num,
                           lookahead=pipelined)
      if first is not None:
        first = first.result()
    try:
      for f, st in loop:
        if f == 0 and first is not None:
          p = first
        else:
          p = maker.dispatch(f, f * prepared.spec.frame_dt, st)
        flush()  # frame f - 1, while the device works on f + 1 and f
        pending = p
        if not pipelined:
          flush()
      flush()
    except mpm.SimulationError as e:
      # Every frame before the failing one is written, as without the
      # pipeline.
      flush()
      raise _pipeline_fix(e, prepared) from None
  except BaseException:
    # (the writers are closed, what they finished kept; an error of theirs
    # in closing is logged, and the loop's error is the one raised)
    out_lib.close_after_failure(sink)
    raise
  t3 = time.perf_counter()
  files = sink.close()
  timings['write'] += time.perf_counter() - t3
  timings['compile'] += loop.compile_s
  timings['simulate'] = loop.sim_s
  timings['total'] = time.perf_counter() - t_start
  return RunOutput(
    gaussian_positions=np.stack(positions),
    sim_rows=np.asarray(prepared.sim_rows),
    particle_positions=np.stack(particles),
    times=np.arange(loop.frames + 1) * loop.config.frame_dt, files=files,
    timings=timings, particle_substeps_per_s=loop.substeps_per_s,
    render_stats=(dict(capacities=maker.capacities, reruns=maker.reruns)
                  if maker.render else {}))


def save_trajectory(path: str, out: RunOutput) -> None:
  """Writes a :class:`RunOutput` as ``trajectory.npz`` (see
  :class:`~physsplat_jax.io.outputs.TrajectoryOutput`)."""
  w = out_lib.TrajectoryOutput(path, out.sim_rows)
  for i, t in enumerate(out.times):
    w.write(out_lib.Frame(index=i, time=float(t),
                          positions=out.gaussian_positions[i],
                          particles=out.particle_positions[i]))
  w.close()


