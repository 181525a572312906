"""Training MPDP through the simulator, and fitting E to observations.

Both go through the package pipeline, ``physsplat_jax.pipeline.simulate``
(MPDP field -> per-driver materials -> ``physsplat_jax.mpm`` MLS-MPM
rollout -> deformed Gaussians -> optional differentiable rendering):

  X(theta) = simulate(Params(mpdp=theta, ...), prepared, config).means
  L(theta) = mean_{t >= 1, k} |X_tk(theta) - X*_tk|^2 / h^2      (h = dx)

The targets ``X*`` are simulated from the same prepared scene with the
ground-truth heterogeneous field of the synthetic object
(:mod:`physsplat_jax.mpdp.synthetic`, documented rules) injected through
``simulate(..., field=gt)``: each driving particle takes the rule's value
at its nearest synthetic point (:func:`synthetic.field_at`). The mean-only
baseline is ``field = 1``, exactly what the zero-initialised network
predicts.

Scenes (:func:`make_cantilever`): a synthetic tapered beam
(:func:`synthetic.make_beam`) scaled to ``length`` metres, its root face at
x = 0, Gaussians at its sample points (coloured root to tip), plus a fixed
``wall`` object around the root that the pipeline turns into a sticky
anchor box. The beam sags under gravity from rest. Every beam is placed so
that its bounding box has the same centre and the same largest side, so all
tasks of a :class:`TaskConfig` share one static ``SimSpec``: one compilation
serves every scene (drivers are chosen by K-means with a fixed budget).

:func:`fit_material` recovers E from an observed trajectory (Gaussian
centres) or from rendered frames (``render='differentiable'``): the unknowns
are the object's log-multiplier of E (``Params.log_scale``) and a smooth
log-field (a polynomial in the normalised driver rest positions, passed as
``field``), fitted by L-BFGS (or Adam) through the rollout (and the
renderer).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import time
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax

from physsplat_jax import atomic_files
from physsplat_jax import cameras as cam_lib
from physsplat_jax import gaussians as gs
from physsplat_jax import pipeline as pl
from physsplat_jax.mpdp import model as model_lib
from physsplat_jax.mpdp import synthetic
from physsplat_jax.mpdp import train as train_lib
from physsplat_jax.render import images as render_images
from physsplat_jax.render import raster
from physsplat_jax.training import checks
from physsplat_jax.training import optim
from physsplat_jax.training.checks import DivergedError as DivergedError
from physsplat_jax.training.checks import TrainingError as TrainingError
from physsplat_jax.types import Array
from physsplat_jax.types import Gaussians
from physsplat_jax.types import ObjectInfo
from physsplat_jax.types import Scene
from physsplat_jax.types import make_camera



@dataclasses.dataclass(frozen=True)
class TaskConfig:
  """Static description of the synthetic cantilever tasks (SI units).

  Attributes:
    num_gaussians: Gaussians of the beam (its synthetic sample points).
    num_particles: driving particles (K-means budget; fixed, so every
      scene has the same shapes).
    length: beam length [m].
    E, nu, rho: the beam's mean properties [Pa, -, kg/m^3] (what
      perception would give; the ground-truth field multiplies them).
    model: constitutive model of the beam.
    num_frames, fps: frames simulated after the rest frame, frame rate.
    substeps_per_frame: MPM substeps per frame (fixed so that targets and
      predictions share one time step).
    grid_res: MPM grid cells per axis.
    margin: free space around the beam, a fraction of its length per side.
    gaussian_scale: standard deviation of the Gaussians, a fraction of the
      beam length.
    width, height: rendered frame size [pixels] (video fits).
    wall_seed: seed of the wall's Gaussians (equal in every task).
    dtype: 'float64' (default; needs ``jax_enable_x64``) or 'float32': the
      dtype the prepared scene and the MPM run in. float32 reverse passes
      can overflow to NaN in the MPM grid update when a particle sits
      within ~1e-5 cells of a half-cell plane on two axes (a node mass of
      ~1e-20 kg whose 1/m^2 overflows); float64 does not, at ~1.3x the
      cost.

  Every field is checked when the config is made
  (:func:`~.checks.check_task_config`: a bad one raises TrainingError).
  """

  num_gaussians: int = 384
  num_particles: int = 192
  length: float = 0.5
  E: float = 3e5
  nu: float = 0.3
  rho: float = 1000.0
  model: str = 'fixed_corotated'
  num_frames: int = 10
  fps: float = 24.0
  substeps_per_frame: int = 50
  grid_res: int = 20
  margin: float = 0.75
  gaussian_scale: float = 0.024
  width: int = 64
  height: int = 48
  wall_seed: int = 1234
  dtype: str = 'float64'

  def __post_init__(self):
    checks.check_task_config(self)

  def pipeline_config(self, render: str = 'none',
                      render_config: raster.RenderConfig | None = None
                      ) -> pl.PipelineConfig:
    """The :class:`~physsplat_jax.pipeline.PipelineConfig` of the tasks."""
    return pl.PipelineConfig(
      num_frames=self.num_frames, fps=self.fps,
      substeps_per_frame=self.substeps_per_frame, grid_res=self.grid_res,
      margin=self.margin, ground='none', sampling='kmeans',
      max_particles=self.num_particles, fill=True, use_mpdp=True,
      render=render, width=self.width, height=self.height,
      render_config=render_config or raster.RenderConfig())

  @classmethod
  def from_dict(cls, d) -> 'TaskConfig':
    """From a dict / ConfigDict; unknown keys raise ``ValueError``."""
    d = dict(d.to_dict() if hasattr(d, 'to_dict') else d)
    names = {f.name for f in dataclasses.fields(cls)}
    bad = sorted(set(d) - names)
    if bad:
      raise TrainingError(f'unknown TaskConfig fields {bad}; valid: '
                          f'{sorted(names)}')
    return cls(**d)


@dataclasses.dataclass(frozen=True)
class Task:
  """One scene with its ground truth and target observations.

  Attributes:
    seed: beam seed.
    scene: the :class:`~physsplat_jax.types.Scene` (beam + wall).
    obj: the synthetic beam in scene coordinates (GT rule inputs).
    config: the pipeline config the task was prepared and simulated with.
    prepared: :func:`physsplat_jax.pipeline.prepare_scene` output.
    params: default :class:`~physsplat_jax.pipeline.Params` (``mpdp`` None).
    field: (N, 3) ground-truth multipliers (E, nu, rho) per driver.
    target: (T+1, Ks, 3) Gaussian centres simulated with ``field``.
    images: (T+1, H, W, 3) target frames, or None (``render='none'``).
  """

  seed: int
  scene: Scene
  obj: synthetic.SyntheticObject
  config: pl.PipelineConfig
  prepared: pl.PreparedScene
  params: pl.Params
  field: Array
  target: Array
  images: Array | None


# --------------------------------------------------------------- scenes


def _beam_colors(x: np.ndarray) -> np.ndarray:
  """Root (dark red) to tip (yellow) by ``x`` in [0, 1]."""
  x = np.clip(x, 0.0, 1.0)[:, None]
  return (1 - x) * np.array([0.6, 0.1, 0.1]) + x * np.array([0.95, 0.8, 0.2])


def make_cantilever(seed: int, tc: TaskConfig = TaskConfig()):
  """A synthetic cantilever anchored in a fixed wall (scene units = m).

  The beam (:func:`synthetic.make_beam`, E/nu/rho/model from ``tc``) is
  scaled uniformly to ``tc.length`` along x, its root face at x = 0 and its
  y/z bounding box centred on 0; the wall is a box of Gaussians
  ``[-0.08, 0.08] x [-0.24, 0.24] x [-0.36, 0.36] * length`` (same in every
  task) that ``prepare_scene`` turns into a sticky anchor box.

  Args:
    seed: beam seed.
    tc: task config.

  Returns:
    ``(scene, materials, obj)``: the scene, one material per object
    (beam, wall) and the beam as a :class:`synthetic.SyntheticObject` in
    scene coordinates.
  """
  L = float(tc.length)
  o = synthetic.make_beam(seed, tc.num_gaussians, tc.E, tc.nu, tc.rho,
                          tc.model)
  p = o.points.astype(np.float64)
  s = L / float(np.ptp(p[:, 0]))
  centre = 0.5 * (p.min(0) + p.max(0))
  offset = -s * np.array([p[:, 0].min(), centre[1], centre[2]])
  obj = synthetic.transform_object(o, s, offset)
  # Coordinates on a 2^-20 m lattice: the bounding box is then exactly
  # [0, L] x [-a, a] x [-b, b] in float32 too, so every beam gives the same
  # grid placement (one compilation for all tasks).
  q = 2.0 ** 20
  beam = np.round(obj.points.astype(np.float64) * q) / q
  beam[:, 1:] -= 0.5 * (beam[:, 1:].min(0) + beam[:, 1:].max(0))
  obj = dataclasses.replace(obj, points=beam.astype(np.float32))
  rng = np.random.default_rng(tc.wall_seed)
  half = np.array([0.08, 0.24, 0.36]) * L
  nwall = max(32, tc.num_gaussians // 6)
  wall = rng.uniform(-half, half, (nwall, 3))
  means = np.concatenate([beam, wall])
  k = len(means)
  rgb = np.concatenate([_beam_colors(beam[:, 0] / L),
                        np.full((nwall, 3), 0.55)])
  g = Gaussians(
    means=jnp.asarray(means, jnp.float32),
    log_scales=jnp.full((k, 3), np.log(tc.gaussian_scale * L), jnp.float32),
    quats=jnp.tile(jnp.asarray([1.0, 0.0, 0.0, 0.0], jnp.float32), (k, 1)),
    opacity_logits=jnp.full((k,), 3.0, jnp.float32),
    sh=jnp.asarray(gs.rgb_to_sh_dc(rgb), jnp.float32)[:, None, :])
  ids = np.r_[np.zeros(len(beam), np.int32), np.ones(nwall, np.int32)]
  # A side view (looking along +y) that sees the beam sag in its plane.
  dist = 3.2 * L
  view = cam_lib.look_at([0.5 * L, -dist, -0.2 * L], [0.5 * L, 0.0, -0.2 * L])
  f = 0.5 * tc.width * dist / (1.2 * L)
  camera = make_camera(view, f, f, tc.width, tc.height, near=0.1 * L,
                       far=10.0 * dist)
  scene = Scene(gaussians=g, object_ids=jnp.asarray(ids),
                objects=(ObjectInfo('beam'), ObjectInfo('wall', fixed=True)),
                cameras=(camera,), up_axis='z', meters_per_unit=1.0,
                name=f'cantilever_{seed}')
  materials = (pl.ObjectMaterial(tc.model, tc.E, tc.nu, tc.rho),
               pl.ObjectMaterial('rigid', 1e9, 0.3, 1000.0, rigid=True))
  return scene, materials, obj


def driver_field(obj: synthetic.SyntheticObject,
                 prepared: pl.PreparedScene) -> np.ndarray:
  """(N, 3) float32 ground-truth multipliers at the driving particles.

  Single-object scenes: the drivers (simulation frame) are mapped back to
  scene coordinates and take the rule's value at their nearest synthetic
  point (:func:`synthetic.field_at`), scaled to a volume-weighted mean of
  exactly 1 over the drivers, as ``pipeline.simulate`` scales the MPDP
  field it trains (so the truth is a field the network can give).
  """
  if prepared.num_objects != 1:
    raise TrainingError('driver_field: scenes with one movable object only; '
                        f'this one has {prepared.num_objects}.')
  x = np.asarray(prepared.frame.to_scene(prepared.x0), np.float64)
  f = synthetic.field_at(obj, x)
  v = np.asarray(prepared.volume, np.float64)[:, None]
  return (f * (v.sum() / (v * f).sum(0))).astype(np.float32)


def default_params(prepared: pl.PreparedScene,
                   config: pl.PipelineConfig) -> pl.Params:
  """:func:`pipeline.init_params` without MPDP weights (``mpdp=None``)."""
  return pl.init_params(prepared, dataclasses.replace(config, use_mpdp=False))


def make_task(seed: int, tc: TaskConfig = TaskConfig(),
              render: str = 'none', render_margin: float = 2.0) -> Task:
  """Prepares a cantilever and simulates its ground-truth target.

  Args:
    seed: beam seed.
    tc: task config.
    render: 'none', or 'differentiable' to also render target frames (the
      rasterizer is sized on the rest scene with ``render_margin``).
    render_margin: head-room of the rasterizer capacity (the beam moves).

  Returns:
    A :class:`Task`.

  Raises:
    DivergedError (a FloatingPointError): the target simulation is not
      finite (raise ``tc.substeps_per_frame``).
  """
  checks.check('make_task', [('seed', seed, 'int>=0')])  # (NumPy's rule)
  scene, materials, obj = make_cantilever(seed, tc)
  rc = None
  if render != 'none':
    rc = render_images.fit_render_config(scene.gaussians, scene.cameras[0],
                                  margin=render_margin)
  config = tc.pipeline_config(render, rc)
  if tc.dtype == 'float64' and not jax.config.jax_enable_x64:
    raise TrainingError("TaskConfig.dtype='float64' needs x64: call "
                        "jax.config.update('jax_enable_x64', True) first, or "
                        "use dtype='float32'.")
  dtype = jnp.dtype(tc.dtype)
  prepared, _ = pl.prepare_scene(jax.random.PRNGKey(config.seed), scene,
                                 materials, config)
  prepared = prepared.astype(dtype)
  params = default_params(prepared, config)  # in prepared's dtype
  field = jnp.asarray(driver_field(obj, prepared), dtype)
  traj = pl.simulate_jit(params, prepared, config, field=field)
  target = traj.means
  if not bool(jnp.all(jnp.isfinite(target))):
    raise DivergedError(
      f'cantilever {seed}: the ground-truth simulation is not finite; raise '
      f'TaskConfig.substeps_per_frame (now {tc.substeps_per_frame}).')
  images = traj.images
  if images is not None and bool(jnp.any(traj.render_overflow)):
    raise TrainingError(f'cantilever {seed}: the rasterizer overflowed; raise '
                        'render_margin.')
  return Task(seed=seed, scene=scene, obj=obj, config=config,
              prepared=prepared, params=params, field=field, target=target,
              images=images)


def make_tasks(seeds: Sequence[int], tc: TaskConfig = TaskConfig(),
               render: str = 'none') -> list[Task]:
  """:func:`make_task` for each seed."""
  return [make_task(int(s), tc, render) for s in seeds]


# ----------------------------------------------------------------- losses


def trajectory_error(means: Array, target: Array,
                     prepared: pl.PreparedScene) -> Array:
  """Mean squared distance of the Gaussian centres over frames 1..T, in
  units of the grid spacing squared (dx^2)."""
  h = prepared.spec.dx / prepared.frame.scale  # dx in scene units
  d2 = jnp.sum((means[1:] - target[1:]) ** 2, -1)
  return jnp.mean(d2) / h**2


def image_error(images: Array, target: Array) -> Array:
  """Mean squared RGB error over frames 1..T."""
  return jnp.mean((images[1:] - target[1:]) ** 2)


def make_loss(config: pl.PipelineConfig) -> Callable:
  """``loss_fn(mpdp_params, base, prepared, target) -> L`` [dx^2].

  Simulates ``base.replace(mpdp=mpdp_params)`` with
  :func:`physsplat_jax.pipeline.simulate` (MPDP predicts the field), so
  gradients reach the network weights through the whole pipeline.
  """
  config = dataclasses.replace(config, render='none')

  def loss_fn(mpdp_params, base, prepared, target):
    traj = pl.simulate(base.replace(mpdp=mpdp_params), prepared, config)
    return trajectory_error(traj.means, target, prepared)

  return loss_fn


def _check_same_spec(tasks: Sequence[Task]) -> pl.PipelineConfig:
  if not tasks:
    raise TrainingError('no tasks given')
  config = dataclasses.replace(tasks[0].config, render='none',
                               render_config=raster.RenderConfig())
  for t in tasks[1:]:
    if dataclasses.replace(t.config, render='none',
                           render_config=raster.RenderConfig()) != config:
      raise TrainingError(f'task {t.seed} has a different pipeline config; '
                          'build all tasks from one TaskConfig.')
  return config


def _finite(tree) -> bool:
  return all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(tree))


def make_optimizer(learning_rate: float, grad_clip: float = 1.0,
                   num_steps: int | None = None):
  """Adam with global-norm clipping (cosine decay to 10% when
  ``num_steps`` is given)."""
  lr = learning_rate
  if num_steps:
    lr = optax.cosine_decay_schedule(learning_rate, num_steps, alpha=0.1)
  return optax.chain(optax.clip_by_global_norm(grad_clip), optax.adam(lr))


@functools.lru_cache(maxsize=8)
def _grad_fn(config: pl.PipelineConfig):
  """Jitted ``value_and_grad`` of :func:`make_loss` (cached per config, so
  repeated runs reuse the compilation)."""
  return jax.jit(jax.value_and_grad(make_loss(config)))


def make_train_step(config: pl.PipelineConfig, tx) -> Callable:
  """Host step ``step_fn(state, tasks) -> (state, loss, per_task)``.

  ``state = {'step', 'params', 'opt_state'}``. The gradient of each task's
  loss (one jitted ``value_and_grad`` shared by all tasks, which have equal
  shapes and static specs) is averaged over the tasks, then one optax
  update is applied. A non-finite loss or gradient raises
  ``DivergedError`` (a ``FloatingPointError``) naming the step (lower the
  learning rate or raise the substeps) instead of writing NaNs into the weights.
  """
  grad_fn = _grad_fn(config)

  @jax.jit
  def apply_fn(state, grads):
    updates, opt_state = tx.update(grads, state['opt_state'],
                                   state['params'])
    return {'step': state['step'] + 1,
            'params': optax.apply_updates(state['params'], updates),
            'opt_state': opt_state}

  def step_fn(state, tasks):
    losses, grads = [], None
    for t in tasks:
      loss, g = grad_fn(state['params'], t.params, t.prepared, t.target)
      losses.append(float(loss))
      grads = g if grads is None else jax.tree.map(jnp.add, grads, g)
    grads = jax.tree.map(lambda x: x / len(tasks), grads)
    if not (np.all(np.isfinite(losses)) and _finite(grads)):
      raise DivergedError(
        f'step {int(state["step"])}: non-finite trajectory loss or gradient '
        f'(losses {losses}); lower the learning rate or raise '
        'substeps_per_frame.')
    return apply_fn(state, grads), float(np.mean(losses)), losses

  return step_fn


def train_through_simulator(params, tasks: Sequence[Task], num_steps: int,
                            learning_rate: float = 1e-3,
                            grad_clip: float = 1.0,
                            log_fn: Callable | None = None):
  """Adam on the mean trajectory loss of ``tasks`` w.r.t. MPDP weights.

  Args:
    params: initial MPDP params (default architecture), e.g.
      ``mpdp.init_params(key)`` (the mean-only baseline) or
      ``mpdp.load_pretrained()``.
    tasks: from :func:`make_tasks` (one :class:`TaskConfig`).
    num_steps: optimisation steps (one gradient over all tasks each).
    learning_rate: Adam step size.
    grad_clip: global-norm clip.
    log_fn: optional ``log_fn(step, loss)`` called on the host.

  Returns:
    ``(params, history)``: trained params and the mean loss [dx^2] before
    each step.
  """
  checks.check_optimizer('train_through_simulator', num_steps,
                         learning_rate, grad_clip)
  config = _check_same_spec(tasks)
  tx = make_optimizer(learning_rate, grad_clip)
  step_fn = make_train_step(config, tx)
  state = {'step': jnp.asarray(0, jnp.int32), 'params': params,
           'opt_state': tx.init(params)}
  history = []
  for i in range(num_steps):
    state, loss, _ = step_fn(state, tasks)
    history.append(loss)
    if log_fn is not None:
      log_fn(i, loss)
  return state['params'], history


# ------------------------------------------------------------- evaluation


@functools.lru_cache(maxsize=8)
def make_error_fns(config: pl.PipelineConfig):
  """Jitted ``(network_error_fn, field_error_fn)``:
  ``network_error_fn(mpdp_params, base, prepared, target)`` and
  ``field_error_fn(field, base, prepared, target)`` [dx^2]."""
  config = dataclasses.replace(config, render='none')
  net = jax.jit(make_loss(config))

  @jax.jit
  def field_fn(field, base, prepared, target):
    traj = pl.simulate(base, prepared, config, field=field)
    return trajectory_error(traj.means, target, prepared)

  return net, field_fn


def trajectory_errors(tasks: Sequence[Task], models: dict[str, Any]
                      ) -> dict[str, list[float]]:
  """Trajectory error [dx^2] per task for each named model.

  Args:
    tasks: from :func:`make_tasks`.
    models: name -> MPDP params, or one of the strings 'baseline'
      (field = 1) and 'truth' (the ground-truth field; error 0).

  Returns:
    name -> list of per-task errors.
  """
  config = _check_same_spec(tasks)
  net_fn, field_fn = make_error_fns(config)
  out = {}
  for name, m in models.items():
    errs = []
    for t in tasks:
      if isinstance(m, str):
        if m not in ('baseline', 'truth'):
          raise TrainingError(f"model {name!r}: unknown {m!r}; use params, "
                              "'baseline' or 'truth'.")
        f = jnp.ones_like(t.field) if m == 'baseline' else t.field
        errs.append(float(field_fn(f, t.params, t.prepared, t.target)))
      else:
        errs.append(float(net_fn(m, t.params, t.prepared, t.target)))
    out[name] = errs
  return out


def predicted_field(mpdp_params, task: Task) -> np.ndarray:
  """(N, 3) field the network predicts for the task's drivers."""
  E, nu, rho = pl.driver_materials(task.params.replace(mpdp=mpdp_params),
                                   task.prepared, task.config)
  m = np.asarray(task.prepared.means)[0]
  return np.stack([np.asarray(E) / m[0], np.asarray(nu) / m[1],
                   np.asarray(rho) / m[2]], -1)


def field_log_rmse(field, task: Task) -> list[float]:
  """RMS log error of a (N, 3) field against the task's truth, per
  channel (E, nu, rho)."""
  d = np.log(np.asarray(field, np.float64)) - np.log(
    np.asarray(task.field, np.float64))
  return [float(v) for v in np.sqrt(np.mean(d ** 2, 0))]


# --------------------------------------------- training with checkpoints


def _check_sim(config) -> None:
  TaskConfig.from_dict(config.task)
  checks.check_sim_config(config)


@train_lib.holds_workdir(_check_sim, TrainingError)
def train_and_evaluate(config, workdir: str) -> dict:
  """Trains MPDP through the simulator with orbax checkpoints and resume.

  ``config`` is the ``sim`` section of ``experiments/configs/mpdp.py``:
  ``task`` (:class:`TaskConfig` fields), ``train_seeds``, ``eval_seeds``,
  ``num_steps``, ``learning_rate``, ``grad_clip``, ``init`` ('zero': the
  mean-only baseline network; 'pretrained': the shipped supervised
  weights), ``checkpoint_every``, ``log_every``, ``max_to_keep``.
  Metrics go to absl logging and ``workdir/metrics.jsonl``; the final
  comparison (baseline, shipped supervised network, simulator-trained
  network and the ground truth on train and held-out beams; field errors;
  timings) is returned and written to ``workdir/simulator.json``.
  Every setting and the workdir are checked first
  (:func:`~.checks.check_sim_config`; TrainingError names the field).
  """
  from absl import logging

  from physsplat_jax.mpdp import pretrained

  tc = TaskConfig.from_dict(config.task)
  checks.check_sim_config(config)
  workdir = train_lib.check_workdir(workdir, TrainingError)
  train_lib.record_config(
    workdir, config.to_dict() if hasattr(config, 'to_dict') else dict(config),
    TrainingError)
  t0 = time.perf_counter()
  train = make_tasks(config.train_seeds, tc)
  held = make_tasks(config.eval_seeds, tc)
  t_tasks = time.perf_counter() - t0
  logging.info('prepared %d train / %d held-out cantilevers in %.1f s',
               len(train), len(held), t_tasks)
  if config.init == 'zero':
    params = model_lib.init_params(jax.random.key(0))
  else:  # 'pretrained' (check_sim_config)
    params = pretrained.load_pretrained()
  pipe_config = _check_same_spec(train + held)
  tx = make_optimizer(config.learning_rate, config.grad_clip,
                      config.num_steps)
  step_fn = make_train_step(pipe_config, tx)
  state = {'step': jnp.asarray(0, jnp.int32), 'params': params,
           'opt_state': tx.init(params)}
  t1 = time.perf_counter()
  with train_lib.checkpoint_manager(workdir, config.max_to_keep,
                                    TrainingError) as mngr:
    state = train_lib.restore_latest(mngr, state, TrainingError)
    train_lib.check_room(mngr, state, TrainingError)
    train_lib.trim_metrics(workdir, int(state['step']))
    try:
      for step in range(int(state['step']), config.num_steps):
        state, loss, per = step_fn(state, train)
        done = step + 1
        if done % config.log_every == 0 or done == config.num_steps:
          rec = {'step': done, 'train_loss': loss, 'per_task': per,
                 'elapsed_s': time.perf_counter() - t1}
          logging.info('sim step %d: %s', done, rec)
          train_lib.append_metrics(workdir, rec, TrainingError)
        if done % config.checkpoint_every == 0 or done == config.num_steps:
          train_lib.save_checkpoint(mngr, done, state, TrainingError)
    except KeyboardInterrupt:  # (Ctrl-C, or SIGTERM in the scripts)
      train_lib.save_interrupted(mngr, state, TrainingError)
      raise
    mngr.wait_until_finished()
  t_train = time.perf_counter() - t1
  models = {'baseline': 'baseline',
            'supervised': pretrained.load_pretrained(),
            'simulator': state['params'], 'truth': 'truth'}
  t2 = time.perf_counter()
  result = {
    'train_seeds': list(config.train_seeds),
    'eval_seeds': list(config.eval_seeds),
    'train': trajectory_errors(train, models),
    'held_out': trajectory_errors(held, models),
    'field_log_rmse_held_out': {
      name: [field_log_rmse(predicted_field(m, t), t) for t in held]
      for name, m in models.items() if not isinstance(m, str)},
    'step': int(state['step']),
    'seconds': {'tasks': t_tasks, 'train': t_train,
                'evaluate': time.perf_counter() - t2},
    'task_config': dataclasses.asdict(tc),
  }
  result['field_log_rmse_held_out']['baseline'] = [
    field_log_rmse(np.ones_like(t.field), t) for t in held]
  atomic_files.write_data(os.path.join(workdir, 'simulator.json'),
                          json.dumps(result, indent=1), TrainingError,
                          what='result')
  result['params'] = state['params']
  return result


# ---------------------------------------------------- material recovery


def poly_basis(x0, degree: int = 2):
  """(N, D) monomials of the normalised coordinates, without the constant.

  Degree 1: x, y, z; degree 2 adds x^2, y^2, z^2, xy, xz, yz (D = 9).
  """
  if degree not in (1, 2):
    raise TrainingError(f'poly_basis: degree={degree!r}; use 1 or 2.')
  x0 = jnp.asarray(x0)
  p = model_lib.normalize_points(x0, jnp.ones(x0.shape[:1], bool))
  cols = [p]
  if degree >= 2:
    i, j = np.triu_indices(3)
    cols.append(p[:, i] * p[:, j])
  return jnp.concatenate(cols, axis=-1)


def fit_material(task: Task, observe: str = 'trajectory',
                 num_steps: int | None = None, learning_rate: float = 0.1,
                 E_init: float = 0.3, field_degree: int = 2,
                 log_fn: Callable | None = None,
                 optimizer: str = 'lbfgs') -> dict:
  """Recovers the beam's E (mean and a smooth field) by gradient descent.

  Unknowns: ``log_E`` (the object's log-multiplier of its mean E,
  ``Params.log_scale[0, 0]``) and the coefficients ``c`` of a smooth
  log-field ``m_E = exp(B c) / mean_V exp(B c)`` (``B``: monomials of the
  normalised driver rest positions up to ``field_degree``; ``mean_V`` the
  volume-weighted mean, as for the pipeline's MPDP field and the truth),
  passed to :func:`physsplat_jax.pipeline.simulate` as ``field``.
  nu and rho stay at their true per-driver values (only E is unknown). A
  free per-driver field is ill-posed at this resolution (it fits the
  observations with unobservable drivers anywhere), hence the smooth
  field. L-BFGS (SciPy's L-BFGS-B on the host around one compiled value
  and gradient; the default), or Adam with cosine
  decay: Adam's steps in log E are about ``learning_rate`` whatever the
  gradient, so it overshoots the minimum and stops where the decayed
  rate leaves it (from 0.3x, E ended 9.8% high after 30 steps and 3.9%
  after 60 on a uniform truth that L-BFGS recovers exactly).

  Args:
    task: from :func:`make_task`; with ``observe='video'`` it must have
      been made with ``render='differentiable'``.
    observe: 'trajectory' (loss on the Gaussian centres [dx^2]) or 'video'
      (mean squared RGB error of the rendered frames, through
      ``physsplat_jax.render.render_differentiable``).
    num_steps: optimiser steps; None: 20 (L-BFGS, which stops sooner
      where its line search lowers the loss no further) or 60 (Adam).
    learning_rate: peak Adam step size (on ``log_E`` and ``c``); unused
      by L-BFGS, whose line search sets the step.
    E_init: initial guess as a fraction of the true mean E, > 0.
    field_degree: 0 (mean only), 1 or 2.
    log_fn: optional ``log_fn(step, loss, E_mean)``.
    optimizer: 'lbfgs' (``scipy.optimize.minimize``'s L-BFGS-B) or 'adam'
      (``optax.adam``).

  The arguments are checked first (:func:`~.checks.check_fit`: a bad one
  raises TrainingError naming it).

  Returns:
    dict: 'E_true', 'E_init', 'E_fit' (means [Pa]), 'E_rel_error',
    'field_E' (N,) fitted multipliers, 'field_log_rmse' and
    'uniform_log_rmse' (RMS log error of m_E vs truth, fitted and uniform),
    'E_point_mare' (mean |E_i - E_i*| / E_i* over drivers), 'history'
    (losses), 'final_loss', 'seconds'.
  """
  if observe not in ('trajectory', 'video'):
    raise TrainingError(f"observe={observe!r}: use 'trajectory' or 'video'.")
  if num_steps is None:
    num_steps = 20 if optimizer == 'lbfgs' else 60
  checks.check_fit(num_steps, learning_rate, E_init, field_degree, optimizer)
  if observe == 'video' and task.images is None:
    raise TrainingError("observe='video' needs a task made with "
                        "render='differentiable' (make_task(..., render=...)).")
  if observe == 'video':
    config = task.config
  else:
    config = dataclasses.replace(task.config, render='none')
  prepared = task.prepared
  n = prepared.num_particles
  basis = (poly_basis(prepared.x0, field_degree) if field_degree > 0
           else jnp.zeros((n, 0), prepared.x0.dtype))
  gt = task.field
  mask = jnp.ones((n,), bool)
  dtype = prepared.x0.dtype
  theta = {'log_E': jnp.log(jnp.asarray(E_init, dtype)),
           'coef': jnp.zeros((basis.shape[1],), dtype)}

  def field_of(th):
    mE = model_lib.normalize_field((basis @ th['coef'])[:, None], mask,
                                   prepared.volume)
    return jnp.concatenate([mE, gt[:, 1:]], axis=-1)

  def loss_fn(th):
    p = task.params.replace(
      log_scale=task.params.log_scale.at[0, 0].set(th['log_E']))
    traj = pl.simulate(p, prepared, config, field=field_of(th))
    if observe == 'video':
      return image_error(traj.images, task.images)
    return trajectory_error(traj.means, task.target, prepared)

  def diverged(i):
    fix = (f'lower learning_rate (now {learning_rate}; fit_material\'s '
           '--learning_rate)' if optimizer == 'adam' else
           f'start closer (E_init, now {E_init}; --E_init)')
    return DivergedError(
      f'fit_material step {i}: non-finite loss or gradient; {fix} '
      'or raise the task\'s substeps_per_frame (now '
      f'{task.config.substeps_per_frame}; --config.sim.task.'
      'substeps_per_frame).')

  history = []  # the loss before each step

  def record(i, loss, th):
    history.append(loss)
    if log_fn is not None:
      log_fn(i, loss, float(jnp.exp(th['log_E'])) * float(
        prepared.means[0, 0]))

  t0 = time.perf_counter()
  if optimizer == 'lbfgs':
    theta, final = optim.lbfgs(jax.jit(jax.value_and_grad(loss_fn)),
                               theta, num_steps, record, diverged)
  else:
    tx = optax.adam(optax.cosine_decay_schedule(learning_rate, num_steps,
                                                alpha=0.05))
    opt = tx.init(theta)

    @jax.jit
    def step(th, o):
      loss, g = jax.value_and_grad(loss_fn)(th)
      u, o = tx.update(g, o, th)
      return optax.apply_updates(th, u), o, loss, g

    for i in range(num_steps):
      new, new_opt, loss, g = step(theta, opt)
      if not (np.isfinite(float(loss)) and _finite(g)):
        raise diverged(i)
      theta, opt = new, new_opt
      record(i, float(loss), theta)
    final = float(jax.jit(loss_fn)(theta))
  E_mean = float(prepared.means[0, 0])
  E_fit = E_mean * float(jnp.exp(theta['log_E']))
  fE = np.asarray(field_of(theta)[:, 0], np.float64)
  tE = np.asarray(gt[:, 0], np.float64)
  return {
    'E_true': E_mean, 'E_init': E_init * E_mean, 'E_fit': E_fit,
    'E_rel_error': abs(E_fit - E_mean) / E_mean,
    'field_E': fE,
    'field_log_rmse': float(np.sqrt(np.mean((np.log(fE) - np.log(tE))**2))),
    'uniform_log_rmse': float(np.sqrt(np.mean(np.log(tE) ** 2))),
    'E_point_mare': float(np.mean(np.abs(E_fit / E_mean * fE - tE) / tE)),
    'history': history, 'final_loss': final,
    'seconds': time.perf_counter() - t0,
  }
