"""One pipeline: ``prepare_scene`` (host, discrete) and ``simulate`` (pure).

PhysSplat (ICCV 2025) end to end::

  materials = perception.perceive_scene(scene, ...)       # MLLM-P3 / library
  prepared = prepare_scene(scene, materials, config, key) # host, not traced
  params = init_params(prepared)                          # differentiable
  out = simulate(params, prepared, config)                # pure, jit-able

``prepare_scene`` does everything that is discrete and never differentiated:
it moves the scene into the simulation frame (metres, +z up), turns fixed
objects into colliders (a support plane under the movable objects, sticky
anchor boxes elsewhere), fills the movable objects' interiors and picks the
driving particles with PGAS (``physsplat_jax.sampling``), binds every
simulated Gaussian to its ``k`` nearest drivers (``physsplat_jax.deform``)
and gathers each object's drivers for the MPDP network.

``simulate(params, prepared, config)`` is a pure function of the
differentiable ``params`` (:class:`Params`: MPDP network weights, per-object
log-multipliers of E, nu, rho, per-object initial velocities):

  field   = MPDP(params.mpdp, object drivers, object means)     (N, 3)
  E, nu, rho = means * exp(params.log_scale) * field            per driver
  x, F    = MLS-MPM rollout (lax.scan over frames and substeps,
            one jax.checkpoint per frame)                       (T+1, N, ...)
  means, covariances, rotations of the Gaussians = deform(x, F)
  images  = render(deformed Gaussians)                          (T+1, H, W, 3)

and :func:`run` is the host-loop version that streams frames to disk with
per-frame progress (``experiments/simulate.py``, ``make demo``).

Frames: the simulation frame is the scene frame rotated so that the scene's
up axis is +z, scaled by ``scene.meters_per_unit`` and shifted so the
simulated region sits inside the grid ``[lower, lower + size]^3``:
``x_sim = s R x_scene + shift``. Everything user-facing (trajectories,
Gaussians, PLY frames) is given back in scene coordinates.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from absl import logging
from flax import struct

from physsplat_jax import deform as deform_lib
from physsplat_jax import gaussians as gs
from physsplat_jax import mpdp
from physsplat_jax import mpm
from physsplat_jax import sampling
from physsplat_jax.render import raster
from physsplat_jax.types import Camera
from physsplat_jax.types import Gaussians
from physsplat_jax.types import Scene

Array = jax.Array


class PipelineError(ValueError):
  """The scene or config cannot be simulated; the message names the fix."""


# ------------------------------------------------------------------- configs


@dataclasses.dataclass(frozen=True)
class ObjectMaterial:
  """The material of one object, as the pipeline consumes it.

  :class:`physsplat_jax.perception` produces these (``MaterialChoice`` has the
  same fields); any object with these attributes works.

  Attributes:
    model: canonical constitutive model ('fixed_corotated', ..., 'rigid').
    E: mean Young's modulus [Pa] (simulation preset).
    nu: mean Poisson's ratio in [0, 0.5).
    rho: mean density [kg/m^3].
    rigid: the object moves as one rigid body.
    params: other model parameters, sorted ``((name, value), ...)``, e.g.
      yield_stress.
    material_key: material-library key, or ''.
    source: which path chose it ('mllm', 'library', 'config', 'override').
    reason: one line saying why.
  """

  model: str
  E: float
  nu: float
  rho: float
  rigid: bool = False
  params: tuple[tuple[str, float], ...] = ()
  material_key: str = ''
  source: str = 'config'
  reason: str = ''


@dataclasses.dataclass(frozen=True)
class ForceSpec:
  """A force acting on the simulation (static description).

  Attributes:
    kind: 'impulse' (a velocity change applied once, at ``start``) or
      'point' (a constant acceleration inside a ball over a time window, as
      PhysDreamer's poke).
    object: name of the object it acts on ('' = every movable object).
    vector: (3,) velocity change [m/s] for 'impulse', acceleration [m/s^2]
      for 'point', in the scene's axes (not scaled by meters_per_unit).
    point: (3,) centre of the ball in scene coordinates (for 'point'); None
      means the object's centre.
    radius: ball radius [m] (for 'point').
    start, end: time window [s].
  """

  kind: str = 'impulse'
  object: str = ''
  vector: tuple[float, float, float] = (0.0, 0.0, 0.0)
  point: tuple[float, float, float] | None = None
  radius: float = 0.05
  start: float = 0.0
  end: float = 0.0


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
  """Static (hashable) settings of the whole pipeline.

  Attributes:
    num_frames: frames to simulate (the output has ``num_frames + 1``).
    fps: frames per second of the output video [1/s].
    substeps_per_frame: MPM substeps per frame; None picks them from the
      CFL bound of the softest/stiffest deformable material.
    cfl: Courant number used when choosing substeps.
    grid_res: MPM grid cells per axis.
    margin: free space around the movable objects, as a fraction of their
      size, on each side (the grid is a cube).
    gravity: gravitational acceleration [m/s^2] along -up (0 disables).
    ground: contact with the support plane: 'slip' (separating, with
      friction), 'sticky' or 'none'.
    friction: Coulomb friction coefficient of the support plane.
    sampling: driving-particle method: 'pgas', 'uniform' or 'kmeans'.
    particles_per_cell: target driving particles per grid cell of the
      stiffest material (sets PGAS's base radius); PGAS adds more where soft
      or curved.
    max_particles: upper bound on the number of driving particles.
    fill: fill object interiors with candidate particles.
    bind_k: drivers per Gaussian for the deformation.
    use_driver_F: deform Gaussians with the drivers' interpolated F instead
      of the local affine fit of their positions.
    use_mpdp: per-point material fields from MPDP (else uniform means).
    forces: tuple of :class:`ForceSpec`.
    initial_velocity: ``((object_name, (vx, vy, vz)), ...)`` [m/s, scene
      axes]; '' as a name means every movable object.
    width, height: rendered frame size [pixels].
    camera_index: which scene camera renders (-1: a fitted default).
    background: RGB in [0, 1].
    render: 'fast' (render-only path), 'differentiable' or 'none'.
    render_config: static rasterizer settings (capacities are re-sized on
      the host by :func:`run`; :func:`simulate` reports overflow).
    remat_frames: ``jax.checkpoint`` each frame (memory ~ frames).
    seed: PRNG seed for filling and sampling.
  """

  num_frames: int = 60
  fps: float = 30.0
  substeps_per_frame: int | None = None
  cfl: float = 0.4
  grid_res: int = 48
  margin: float = 0.3
  gravity: float = 9.8
  ground: str = 'slip'
  friction: float = 0.4
  sampling: str = 'pgas'
  particles_per_cell: float = 4.0
  max_particles: int = 40_000
  fill: bool = True
  bind_k: int = 8
  use_driver_F: bool = False
  use_mpdp: bool = True
  forces: tuple[ForceSpec, ...] = ()
  initial_velocity: tuple[tuple[str, tuple[float, float, float]], ...] = ()
  width: int = 512
  height: int = 384
  camera_index: int = 0
  background: tuple[float, float, float] = (1.0, 1.0, 1.0)
  render: str = 'fast'
  render_config: raster.RenderConfig = raster.RenderConfig()
  remat_frames: bool = True
  seed: int = 0

  def __post_init__(self):
    checks = [
      (self.num_frames >= 1, 'num_frames', 'use >= 1'),
      (self.fps > 0, 'fps', 'use > 0'),
      (self.substeps_per_frame is None or self.substeps_per_frame >= 1,
       'substeps_per_frame', 'use >= 1 or None (automatic)'),
      (0 < self.cfl <= 1, 'cfl', 'use a Courant number in (0, 1]'),
      (8 <= self.grid_res <= 512, 'grid_res', 'use 8..512'),
      (self.margin >= 0, 'margin', 'use >= 0'),
      (self.ground in ('slip', 'sticky', 'none'), 'ground',
       "use 'slip', 'sticky' or 'none'"),
      (self.friction >= 0, 'friction', 'use >= 0'),
      (self.sampling in ('pgas', 'uniform', 'kmeans'), 'sampling',
       "use 'pgas', 'uniform' or 'kmeans'"),
      (self.particles_per_cell > 0, 'particles_per_cell', 'use > 0'),
      (self.max_particles >= 8, 'max_particles', 'use >= 8'),
      (self.bind_k >= 4, 'bind_k', 'use >= 4'),
      (self.width >= 1 and self.height >= 1, 'width/height', 'use >= 1'),
      (self.render in ('fast', 'differentiable', 'none'), 'render',
       "use 'fast', 'differentiable' or 'none'"),
    ]
    for ok, name, fix in checks:
      if not ok:
        raise PipelineError(
          f'PipelineConfig.{name}={getattr(self, name.split("/")[0])!r} is '
          f'invalid: {fix}.')
    for f in self.forces:
      if f.kind not in ('impulse', 'point'):
        raise PipelineError(
          f"ForceSpec.kind={f.kind!r}: use 'impulse' or 'point'.")

  @property
  def frame_dt(self) -> float:
    return 1.0 / self.fps


# -------------------------------------------------------------- frame maps


def up_rotation(up: np.ndarray) -> np.ndarray:
  """Proper rotation (3, 3) that maps the unit vector ``up`` to +z."""
  u = np.asarray(up, np.float64)
  u = u / np.linalg.norm(u)
  z = np.array([0.0, 0.0, 1.0])
  c = float(u @ z)
  if c > 1 - 1e-12:
    return np.eye(3)
  if c < -1 + 1e-12:
    return np.diag([1.0, -1.0, -1.0])  # 180 degrees about x
  v = np.cross(u, z)
  s = np.linalg.norm(v)
  vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
  return np.eye(3) + vx + vx @ vx * ((1 - c) / s**2)


class SimFrame(struct.PyTreeNode):
  """``x_sim = scale * rotation @ x_scene + shift`` (metres, +z up).

  Attributes:
    rotation: (3, 3) proper rotation (scene up -> +z).
    scale: () metres per scene unit.
    shift: (3,) [m].
  """

  rotation: Array
  scale: Array
  shift: Array

  def to_sim(self, x: Array) -> Array:
    return self.scale * (x @ self.rotation.T) + self.shift

  def to_scene(self, x: Array) -> Array:
    return ((x - self.shift) / self.scale) @ self.rotation

  def vector_to_sim(self, v: Array) -> Array:
    """Directions/velocities in scene axes [m/s] -> simulation axes."""
    return v @ self.rotation.T

  def covariance_to_scene(self, cov: Array) -> Array:
    R = self.rotation
    return (R.T @ cov @ R) / self.scale**2

  def rotation_to_scene(self, rot: Array) -> Array:
    R = self.rotation
    return R.T @ rot @ R


def transform_gaussians(g: Gaussians, frame: SimFrame) -> Gaussians:
  """The same Gaussians expressed in the simulation frame."""
  q = gs.rotmat_to_quat(jnp.asarray(frame.rotation, g.quats.dtype))
  quats = gs.quat_multiply(jnp.broadcast_to(q, g.quats.shape),
                           gs.normalize_quat(g.quats))
  return g.replace(
    means=frame.to_sim(g.means).astype(g.means.dtype),
    log_scales=(g.log_scales + jnp.log(frame.scale)).astype(
      g.log_scales.dtype),
    quats=quats.astype(g.quats.dtype),
  )


# ----------------------------------------------------------------- colliders


@dataclasses.dataclass(frozen=True)
class Colliders:
  """Fixed objects turned into boundary conditions (simulation frame).

  Attributes:
    ground_z: height of the support plane [m], or None.
    anchors: ((lo (3,), hi (3,)), ...) sticky boxes [m]: fixed objects that
      are not a plane under the movable ones (e.g. the pot of a plant).
    notes: one line per fixed object saying what it became (for reports;
      not part of equality, so it never causes a recompilation).
  """

  ground_z: float | None
  anchors: tuple[tuple[tuple[float, ...], tuple[float, ...]], ...]
  notes: tuple[str, ...] = dataclasses.field(default=(), compare=False)


def find_colliders(means_sim: np.ndarray, object_ids: np.ndarray,
                   movable: Sequence[int], fixed: Sequence[int],
                   names: Sequence[str], tol: float) -> Colliders:
  """Classifies fixed objects into a support plane and anchor boxes.

  A fixed object whose top (99th height percentile of its Gaussians under
  the movable objects' footprint) lies at or below the lowest movable point
  (+ ``tol``) is a support: the highest such top becomes the ground plane.
  Any other fixed object that reaches into the movable objects' footprint is
  an anchor box (its bounding box; grid velocity zero inside, as
  PhysGaussian's fixed ``cuboid``). Without a support the ground is the
  lowest movable point.
  """
  mov = np.isin(object_ids, np.asarray(movable, np.int64))
  if not mov.any():
    raise PipelineError('the scene has no movable object to simulate; mark '
                        'at least one object as not fixed.')
  lo = means_sim[mov].min(0)
  hi = means_sim[mov].max(0)
  pad = 0.1 * float(np.max(hi[:2] - lo[:2])) + tol
  ground = None
  anchors = []
  notes = []
  for o in fixed:
    pts = means_sim[object_ids == o]
    if len(pts) == 0:
      continue
    under = np.all((pts[:, :2] >= lo[:2] - pad) & (pts[:, :2] <= hi[:2] + pad),
                   axis=1)
    if not under.any():
      notes.append(f'{names[o]}: fixed, away from the movable objects '
                   '(static, not simulated)')
      continue
    top = float(np.percentile(pts[under, 2], 99.0))
    if top <= lo[2] + tol:
      if ground is None or top > ground:
        ground = top
      notes.append(f'{names[o]}: fixed support, ground plane at z={top:.4f} m')
    else:
      blo = pts[under].min(0)
      bhi = pts[under].max(0)
      anchors.append((tuple(float(v) for v in blo),
                      tuple(float(v) for v in bhi)))
      notes.append(f'{names[o]}: fixed anchor box {np.round(blo, 4)} .. '
                   f'{np.round(bhi, 4)} m (sticky)')
  if ground is None:
    ground = float(lo[2])
    notes.append(f'no fixed support under the movable objects: ground plane '
                 f'at their lowest point z={ground:.4f} m')
  return Colliders(ground_z=ground, anchors=tuple(anchors), notes=tuple(notes))


# ------------------------------------------------------------- preparation


class Params(struct.PyTreeNode):
  """Differentiable inputs of :func:`simulate` (all leaves are arrays).

  Attributes:
    mpdp: MPDP network params (``physsplat_jax.mpdp``), or None for uniform
      per-object materials.
    log_scale: (O, 3) per-object log-multipliers of the mean (E, nu, rho);
      zeros keep the perceived means.
    velocity: (O, 3) initial velocity per movable object [m/s, scene axes].
    forces: (F, 3) force vectors of ``config.forces`` (scene axes).
  """

  mpdp: Any
  log_scale: Array
  velocity: Array
  forces: Array


class PreparedScene(struct.PyTreeNode):
  """Everything :func:`simulate` needs that is not differentiated.

  Array fields are in the simulation frame (metres, +z up) unless noted.

  Attributes:
    gaussians: all Gaussians of the scene (scene coordinates).
    sim_rows: (Ks,) int32 rows of the simulated Gaussians in ``gaussians``.
    rest_means: (Ks, 3) simulated Gaussians' centres [m].
    rest_covs: (Ks, 3, 3) their covariances [m^2].
    binding: Gaussian -> driver binding (simulation frame).
    x0: (N, 3) driver rest positions [m].
    volume: (N,) driver volumes [m^3].
    driver_object: (N,) int32 movable-object index (0..O-1) per driver.
    body_id: (N,) int32 rigid-body index or -1.
    mpdp_index: (O, Nmax) int32 driver rows per object (padded with 0).
    mpdp_mask: (O, Nmax) bool.
    mpdp_means: (O, MEANS_DIM) MPDP condition vectors.
    means: (O, 3) perceived mean (E [Pa], nu, rho [kg/m^3]).
    frame: scene -> simulation map.
    camera: the rendering camera (scene coordinates).
    background: (3,) RGB.
    spec: static :class:`SimSpec` (grid, dt, models, colliders, ...).
  """

  gaussians: Gaussians
  sim_rows: Array
  rest_means: Array
  rest_covs: Array
  binding: deform_lib.Binding
  x0: Array
  volume: Array
  driver_object: Array
  body_id: Array
  mpdp_index: Array
  mpdp_mask: Array
  mpdp_means: Array
  means: Array
  frame: SimFrame
  camera: Camera
  background: Array
  spec: 'SimSpec' = struct.field(pytree_node=False)

  @property
  def num_particles(self) -> int:
    return self.x0.shape[0]

  @property
  def num_objects(self) -> int:
    return self.means.shape[0]


@dataclasses.dataclass(frozen=True)
class SimSpec:
  """Static facts of a prepared scene (hashable; part of the jit key).

  Attributes:
    object_names: names of the movable objects (index = movable index).
    scene_objects: their indices in ``scene.objects``.
    models: constitutive model per movable object.
    rigid: rigid flag per movable object.
    object_params: per object, sorted ((name, value), ...) extra material
      parameters.
    object_ranges: per object, (start, count) of its drivers (contiguous).
    grid_lower: (3,) grid corner [m].
    grid_size: grid side [m].
    grid_res: cells per axis.
    substeps_per_frame: MPM substeps per frame.
    dt: substep [s].
    colliders: :class:`Colliders`.
    force_objects: per force, the movable-object index it acts on (-1 all).
    force_points: per force, the ball centre [m, simulation frame].
    velocity_objects: names given in ``config.initial_velocity``.
  """

  object_names: tuple[str, ...]
  scene_objects: tuple[int, ...]
  models: tuple[str, ...]
  rigid: tuple[bool, ...]
  object_params: tuple[tuple[tuple[str, float], ...], ...]
  object_ranges: tuple[tuple[int, int], ...]
  grid_lower: tuple[float, float, float]
  grid_size: float
  grid_res: int
  substeps_per_frame: int
  dt: float
  colliders: Colliders
  force_objects: tuple[int, ...]
  force_points: tuple[tuple[float, float, float], ...]

  @property
  def dx(self) -> float:
    return self.grid_size / self.grid_res


@dataclasses.dataclass
class PrepareReport:
  """What :func:`prepare_scene` decided, for logs and ``report.json``."""

  objects: list[dict]
  colliders: list[str]
  num_gaussians: int
  num_simulated_gaussians: int
  num_candidates: int
  num_particles: int
  grid: dict
  time_step: dict
  timings: dict


def _movable_and_fixed(scene: Scene, materials) -> tuple[list[int], list[int]]:
  ids = np.asarray(scene.object_ids)
  movable, fixed = [], []
  for o, info in enumerate(scene.objects):
    if not np.any(ids == o):
      continue
    (fixed if info.fixed else movable).append(o)
  if len(materials) != len(scene.objects):
    raise PipelineError(
      f'{len(materials)} materials for {len(scene.objects)} objects of scene '
      f'{scene.name!r}; give one material per object (in scene.objects '
      'order).')
  return movable, fixed


def _check_material(name: str, m) -> None:
  bad = []
  if not (np.isfinite(m.E) and m.E > 0):
    bad.append(f'E={m.E!r} (use > 0 Pa)')
  if not (np.isfinite(m.nu) and 0 <= m.nu < 0.5):
    bad.append(f'nu={m.nu!r} (use 0 <= nu < 0.5)')
  if not (np.isfinite(m.rho) and m.rho > 0):
    bad.append(f'rho={m.rho!r} (use > 0 kg/m^3)')
  if bad:
    raise PipelineError(f'object {name!r}: bad material ' + ', '.join(bad))


def render_camera(scene: Scene, config: PipelineConfig) -> Camera:
  """The camera that renders the video (scene coordinates).

  ``scene.cameras[config.camera_index]`` brought to ``width x height``
  (square pixels kept: the focal length follows the height, the principal
  point is re-centred when the aspect ratio changes), or, with
  ``camera_index=-1`` or no cameras, a camera fitted to the whole scene.
  """
  from physsplat_jax import cameras as cam_lib

  w, h = config.width, config.height
  cam = _render_camera(scene, config, w, h)
  # near/far are static fields of Camera: quantise them (near down, far up,
  # 3 significant digits) so equal views compile once.
  lo = lambda v: float(f'{v * (1 - 1e-3):.3g}')  # noqa: E731
  hi = lambda v: float(f'{v * (1 + 1e-3):.3g}')  # noqa: E731
  return cam.replace(near=lo(cam.near), far=hi(cam.far), name='')


def _render_camera(scene: Scene, config: PipelineConfig, w: int, h: int):
  from physsplat_jax import cameras as cam_lib

  if config.camera_index >= 0 and scene.cameras:
    if config.camera_index >= len(scene.cameras):
      raise PipelineError(
        f'camera_index={config.camera_index} but scene {scene.name!r} has '
        f'{len(scene.cameras)} cameras; use 0..{len(scene.cameras) - 1} or -1 '
        'for a fitted camera.')
    c = scene.cameras[config.camera_index]
    if abs(c.width / c.height - w / h) < 1e-6:
      return c.resized(w, h)
    s = h / c.height
    return c.replace(fx=c.fx * s, fy=c.fy * s, cx=jnp.asarray(w / 2, c.fx.dtype),
                     cy=c.cy * s, width=w, height=h)
  m = np.asarray(scene.gaussians.means)
  lo, hi = np.percentile(m, 1, axis=0), np.percentile(m, 99, axis=0)
  return cam_lib.fit_camera(lo, hi, up=scene.up_vector, width=w, height=h,
                            azimuth=-60.0, elevation=25.0, padding=1.05)


def _wave_speed(E, nu, rho) -> float:
  nu = min(float(nu), 0.499)
  lam = E * nu / ((1 + nu) * (1 - 2 * nu))
  mu = E / (2 * (1 + nu))
  return math.sqrt((lam + 2 * mu) / rho)


def prepare_scene(
  scene: Scene,
  materials: Sequence[Any],
  config: PipelineConfig = PipelineConfig(),
  mpdp_params: Any = None,
) -> tuple[PreparedScene, PrepareReport]:
  """Host-side, non-differentiable preparation of a scene for simulation.

  Args:
    scene: the segmented scene; objects with ``ObjectInfo.fixed`` become
      colliders, the others are simulated.
    materials: one :class:`ObjectMaterial`-like entry per ``scene.objects``
      (fixed objects' entries are only reported).
    config: static settings.
    mpdp_params: MPDP params used to choose the time step for the stiffest
      predicted point (default: the shipped pretrained params when
      ``config.use_mpdp``).

  Returns:
    (prepared scene, report).

  Raises:
    PipelineError: nothing to simulate, a bad material, an object too small
      for the grid, or too few driving particles.
  """
  import time

  timings = {}
  t0 = time.perf_counter()
  movable, fixed = _movable_and_fixed(scene, materials)
  names = [o.name for o in scene.objects]
  if not movable:
    raise PipelineError(
      f'scene {scene.name!r} has no movable object (all are fixed); clear '
      'ObjectInfo.fixed on the objects that should move.')
  for o in movable:
    _check_material(names[o], materials[o])
  ids = np.asarray(scene.object_ids)
  means = np.asarray(scene.gaussians.means, np.float64)

  # Scene -> simulation frame (rotation and scale; shift follows the grid).
  R = up_rotation(scene.up_vector)
  s = float(scene.meters_per_unit)
  x_rs = s * means @ R.T
  mov_mask = np.isin(ids, movable)
  lo, hi = x_rs[mov_mask].min(0), x_rs[mov_mask].max(0)
  ext = hi - lo
  L = float(np.max(ext)) * (1 + 2 * config.margin)
  for _ in range(2):  # vertical room: 4 cells below, 4 above the objects
    L = max(L, float(ext[2]) + 8 * L / config.grid_res)
  # Static values are quantised (grid side to 6 significant digits,
  # positions to 0.1 um) so equal geometry gives an equal SimSpec, i.e. one
  # compilation, whatever the rounding of the input coordinates.
  L = float(f'{L:.6g}')
  dx = L / config.grid_res
  colliders = find_colliders(x_rs, ids, movable, fixed, names, tol=dx)
  ground = colliders.ground_z
  # With a ground the grid floor sits 4 cells under it (3 boundary cells);
  # without one the objects may fall, so the grid is centred on them.
  if config.ground == 'none':
    z0 = 0.5 * (lo[2] + hi[2]) - L / 2
  else:
    z0 = min(lo[2], ground) - 4 * dx
  lower = np.array([0.5 * (lo[0] + hi[0]) - L / 2,
                    0.5 * (lo[1] + hi[1]) - L / 2, z0])
  shift = -lower
  q = lambda v: tuple(round(float(c), 7) for c in v)  # noqa: E731
  # With ground='none' the plane is unused: keep it out of the static spec
  # so scenes that differ only in their lowest point compile once.
  colliders = dataclasses.replace(
    colliders, ground_z=(None if config.ground == 'none'
                         else round(float(ground + shift[2]), 7)),
    anchors=tuple((q(np.add(a, shift)), q(np.add(b, shift)))
                  for a, b in colliders.anchors))
  frame = SimFrame(rotation=jnp.asarray(R, jnp.float32),
                   scale=jnp.asarray(s, jnp.float32),
                   shift=jnp.asarray(shift, jnp.float32))

  # Movable Gaussians in the simulation frame, movable-object indices.
  rows = np.nonzero(mov_mask)[0]
  local = {o: i for i, o in enumerate(movable)}
  local_ids = np.array([local[o] for o in ids[rows]], np.int32)
  g_sim = transform_gaussians(scene.gaussians.subset(rows), frame)
  timings['frame_s'] = time.perf_counter() - t0

  # Candidates (surface + interior fill) and driving particles (PGAS).
  t1 = time.perf_counter()
  key = jax.random.PRNGKey(config.seed)
  k_fill, k_drv = jax.random.split(key)
  obj_ext = max(float(np.max(np.ptp(np.asarray(g_sim.means)[local_ids == i],
                                    axis=0))) for i in range(len(movable)))
  fill_res = int(np.clip(math.ceil(obj_ext / (0.5 * dx)), 16, 128))
  cand = sampling.make_candidates(
    k_fill, g_sim, local_ids, fill=config.fill,
    fill_config=sampling.FillConfig(grid_res=fill_res))
  timings['filling_s'] = time.perf_counter() - t1
  t2 = time.perf_counter()
  base_r = dx * (1.24 / config.particles_per_cell) ** (1.0 / 3.0)
  E_obj = {i: (1e12 if materials[o].rigid else float(materials[o].E))
           for i, o in enumerate(movable)}
  if config.sampling == 'kmeans':
    drv = sampling.select_drivers(k_drv, cand, 'kmeans',
                                  budget=min(config.max_particles, len(cand.x)))
  else:
    drv = sampling.select_drivers(
      k_drv, cand, config.sampling, E=E_obj,
      config=sampling.PGASConfig(base_radius=base_r),
      budget=config.max_particles)
  order = np.argsort(drv.object_ids, kind='stable')
  x0 = drv.x[order]
  vol = drv.volume[order]
  dobj = drv.object_ids[order].astype(np.int32)
  counts = np.bincount(dobj, minlength=len(movable))
  for i, o in enumerate(movable):
    if counts[i] < max(config.bind_k, 8):
      raise PipelineError(
        f'object {names[o]!r} got only {counts[i]} driving particles (need '
        f'>= {max(config.bind_k, 8)}): it is small for the grid (dx = '
        f'{dx:.4f} m); raise grid_res, particles_per_cell or max_particles.')
  starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
  timings['sampling_s'] = time.perf_counter() - t2

  # Binding of the simulated Gaussians to their drivers.
  t3 = time.perf_counter()
  binding = deform_lib.make_binding(
    np.asarray(g_sim.means), x0, k=config.bind_k, dtype=np.float32,
    gauss_object_ids=local_ids, driver_object_ids=dobj)
  timings['binding_s'] = time.perf_counter() - t3

  # MPDP gather: each object's drivers, padded to the largest object.
  nmax = int(counts.max())
  mp_index = np.zeros((len(movable), nmax), np.int32)
  mp_mask = np.zeros((len(movable), nmax), bool)
  for i in range(len(movable)):
    mp_index[i, :counts[i]] = starts[i] + np.arange(counts[i])
    mp_mask[i, :counts[i]] = True
  mats = [materials[o] for o in movable]
  mp_means = np.stack([
    np.asarray(mpdp.encode_means(m.E, m.nu, m.rho, m.model, m.rigid))
    for m in mats])
  obj_means = np.array([[m.E, m.nu, m.rho] for m in mats], np.float64)
  rigid = tuple(bool(m.rigid or m.model == 'rigid') for m in mats)
  bodies = np.cumsum(rigid) - 1
  body_id = np.where(np.asarray(rigid)[dobj], bodies[dobj], -1).astype(
    np.int32)

  # Time step from the stiffest deformable point (MPDP field included).
  t4 = time.perf_counter()
  field_max = np.ones((len(movable), 3))
  if config.use_mpdp:
    params = mpdp.load_pretrained() if mpdp_params is None else mpdp_params
    field = np.asarray(mpdp.predict(params, jnp.asarray(x0[mp_index]),
                                    jnp.asarray(mp_means), jnp.asarray(mp_mask)))
    field = np.where(mp_mask[..., None], field, 1.0)
    field_max = field.max(1)
    field_min = np.where(mp_mask[..., None], field, np.inf).min(1)
  c_max = 0.0
  for i, m in enumerate(mats):
    if rigid[i]:
      continue
    rho_min = m.rho * (field_min[i, 2] if config.use_mpdp else 1.0)
    c_max = max(c_max, _wave_speed(m.E * field_max[i, 0], m.nu, rho_min))
  frame_dt = config.frame_dt
  if config.substeps_per_frame is None:
    if c_max > 0:
      dt_cfl = config.cfl * dx / c_max
    else:
      dt_cfl = config.cfl * dx / max(1.0, config.gravity * frame_dt)
    substeps = max(1, int(math.ceil(frame_dt / dt_cfl)))
  else:
    substeps = int(config.substeps_per_frame)
    if c_max > 0 and frame_dt / substeps > 2 * config.cfl * dx / c_max:
      raise PipelineError(
        f'substeps_per_frame={substeps} gives dt={frame_dt / substeps:.3g} s, '
        f'above the stability bound {config.cfl * dx / c_max:.3g} s for the '
        f'stiffest material (wave speed {c_max:.3g} m/s, dx={dx:.3g} m); use '
        f'substeps_per_frame >= {math.ceil(frame_dt * c_max / (config.cfl * dx))}'
        ' or None (automatic), or lower E.')
  timings['time_step_s'] = time.perf_counter() - t4

  # Forces: target objects and ball centres in the simulation frame.
  f_obj, f_pts = [], []
  for f in config.forces:
    if f.object:
      if f.object not in [names[o] for o in movable]:
        raise PipelineError(
          f'force on object {f.object!r}: no such movable object; choose '
          f'from {[names[o] for o in movable]}')
      oi = [names[o] for o in movable].index(f.object)
    else:
      oi = -1
    f_obj.append(oi)
    if f.point is not None:
      p = np.asarray(frame.to_sim(jnp.asarray(f.point, jnp.float32)))
    else:
      sel = dobj == oi if oi >= 0 else np.ones(len(x0), bool)
      p = x0[sel].mean(0)
    f_pts.append(q(p))
  for name, _ in config.initial_velocity:
    if name and name not in [names[o] for o in movable]:
      raise PipelineError(
        f'initial_velocity for object {name!r}: no such movable object; '
        f'choose from {[names[o] for o in movable]}')

  spec = SimSpec(
    object_names=tuple(names[o] for o in movable),
    scene_objects=tuple(movable),
    models=tuple('rigid' if r else m.model for r, m in zip(rigid, mats)),
    rigid=rigid,
    object_params=tuple(tuple(sorted(dict(m.params).items())) for m in mats),
    object_ranges=tuple((int(a), int(c)) for a, c in zip(starts, counts)),
    grid_lower=(0.0, 0.0, 0.0), grid_size=L, grid_res=config.grid_res,
    substeps_per_frame=substeps, dt=frame_dt / substeps,
    colliders=colliders, force_objects=tuple(f_obj),
    force_points=tuple(f_pts))
  camera = render_camera(scene, config)
  covs = np.asarray(g_sim.covariances)
  prepared = PreparedScene(
    gaussians=scene.gaussians,
    sim_rows=jnp.asarray(rows, jnp.int32),
    rest_means=jnp.asarray(g_sim.means, jnp.float32),
    rest_covs=jnp.asarray(covs, jnp.float32),
    binding=binding,
    x0=jnp.asarray(x0, jnp.float32),
    volume=jnp.asarray(vol, jnp.float32),
    driver_object=jnp.asarray(dobj),
    body_id=jnp.asarray(body_id),
    mpdp_index=jnp.asarray(mp_index),
    mpdp_mask=jnp.asarray(mp_mask),
    mpdp_means=jnp.asarray(mp_means, jnp.float32),
    means=jnp.asarray(obj_means, jnp.float32),
    frame=frame,
    camera=camera,
    background=jnp.asarray(config.background, jnp.float32),
    spec=spec,
  )
  report = PrepareReport(
    objects=[dict(
      name=names[o], fixed=bool(scene.objects[o].fixed),
      material=getattr(materials[o], 'material_key', ''),
      model=getattr(materials[o], 'model', ''),
      E=float(materials[o].E), nu=float(materials[o].nu),
      rho=float(materials[o].rho), rigid=bool(materials[o].rigid),
      source=getattr(materials[o], 'source', ''),
      reason=getattr(materials[o], 'reason', ''),
      num_gaussians=int(np.sum(ids == o)),
      num_particles=(int(counts[local[o]]) if o in local else 0))
      for o in range(len(scene.objects))],
    colliders=list(colliders.notes),
    num_gaussians=int(scene.gaussians.num),
    num_simulated_gaussians=int(len(rows)),
    num_candidates=int(len(cand.x)),
    num_particles=int(len(x0)),
    grid=dict(res=config.grid_res, size_m=L, dx_m=dx),
    time_step=dict(substeps_per_frame=substeps, dt_s=frame_dt / substeps,
                   max_wave_speed_m_s=c_max, cfl=config.cfl),
    timings=timings,
  )
  logging.info('prepared %r: %d particles for %d Gaussians of %d objects, '
               'grid %d^3 (dx %.4f m), %d substeps/frame (dt %.3g s)',
               scene.name, len(x0), len(rows), len(movable), config.grid_res,
               dx, substeps, frame_dt / substeps)
  return prepared, report


def init_params(prepared: PreparedScene, config: PipelineConfig,
                mpdp_params: Any = None) -> Params:
  """Default :class:`Params`: pretrained MPDP, perceived means, the config's
  initial velocities and force vectors."""
  if config.use_mpdp:
    mp = mpdp.load_pretrained() if mpdp_params is None else mpdp_params
  else:
    mp = None
  names = prepared.spec.object_names
  vel = np.zeros((len(names), 3), np.float32)
  for name, v in config.initial_velocity:
    if name:
      vel[names.index(name)] = v
    else:
      vel[:] = v
  forces = np.array([f.vector for f in config.forces], np.float32).reshape(
    len(config.forces), 3)
  return Params(mpdp=mp, log_scale=jnp.zeros((len(names), 3), jnp.float32),
                velocity=jnp.asarray(vel), forces=jnp.asarray(forces))


# ---------------------------------------------------------------- simulation


class Trajectory(struct.PyTreeNode):
  """Output of :func:`simulate` (scene coordinates; axis 0 is frames).

  Attributes:
    x: (T+1, N, 3) driving-particle positions.
    means: (T+1, Ks, 3) simulated Gaussians' centres.
    covariances: (T+1, Ks, 3, 3) their covariances ``F Sigma F^T``.
    rotations: (T+1, Ks, 3, 3) their local rotations (SH view direction).
    images: (T+1, H, W, 3) rendered frames, or None (``render='none'``).
    render_overflow: (T+1,) bool, True where a frame dropped Gaussians
      (re-size ``config.render_config`` or use :func:`run`).
    materials: per-driver E, nu, rho actually simulated, each (N,).
  """

  x: Array
  means: Array
  covariances: Array
  rotations: Array
  images: Array | None
  render_overflow: Array | None
  materials: tuple[Array, Array, Array]


def make_sim_config(spec: SimSpec, config: PipelineConfig,
                    dtype: str = 'float32') -> mpm.SimConfig:
  """The static MPM config of a prepared scene (``dtype``: 'float32' or
  'float64', that of the prepared arrays)."""
  col = spec.colliders
  bcs = []
  if config.ground != 'none' and col.ground_z is not None:
    bcs.append(mpm.SurfaceCollider(
      point=(0.0, 0.0, col.ground_z), normal=(0.0, 0.0, 1.0),
      surface='separate' if config.ground == 'slip' else 'sticky',
      friction=config.friction))
  for lo, hi in col.anchors:
    c = tuple(0.5 * (a + b) for a, b in zip(lo, hi))
    h = tuple(0.5 * (b - a) + 0.5 * spec.dx for a, b in zip(lo, hi))
    bcs.append(mpm.Cuboid(point=c, size=h))
  for f, p in zip(config.forces, spec.force_points):
    if f.kind == 'impulse':
      bcs.append(mpm.PointForce(
        point=p, radius=1e9, force=(0.0, 0.0, 0.0), start_time=f.start,
        end_time=f.start + config.frame_dt, per_particle=False))
    else:
      bcs.append(mpm.PointForce(
        point=p, radius=f.radius, force=(0.0, 0.0, 0.0), start_time=f.start,
        end_time=f.end, per_particle=False))
  nb = int(sum(spec.rigid))
  return mpm.SimConfig(
    grid=mpm.GridSpec(res=spec.grid_res, lower=spec.grid_lower,
                      size=spec.grid_size),
    dt=spec.dt, substeps_per_frame=spec.substeps_per_frame,
    num_frames=config.num_frames, gravity=(0.0, 0.0, -config.gravity),
    models=tuple(dict.fromkeys(spec.models)), boundary_conditions=tuple(bcs),
    num_bodies=nb, body_fixed=(False,) * nb,
    remat_frames=config.remat_frames, dtype=str(np.dtype(dtype)))


def driver_materials(params: Params, prepared: PreparedScene,
                     config: PipelineConfig,
                     field: Array | None = None) -> tuple[Array, Array, Array]:
  """Per-driver (E, nu, rho): MPDP field times the (scaled) object means.

  ``field``, if given, is an (N, 3) array of per-driver multipliers of
  (E, nu, rho) (driver order, e.g. a ground-truth or a fitted field) used
  instead of the MPDP prediction; gradients flow into it as into
  ``params``. Rigid objects keep their means either way.
  """
  spec = prepared.spec
  means = prepared.means * jnp.exp(params.log_scale)  # (O, 3)
  if field is not None:
    if tuple(field.shape) != (prepared.num_particles, 3):
      raise PipelineError(
        f'field has shape {tuple(field.shape)}; give (N, 3) = '
        f'({prepared.num_particles}, 3) multipliers of (E, nu, rho) per '
        'driving particle, in driver order.')
    flat = field.astype(prepared.x0.dtype)
  elif config.use_mpdp and params.mpdp is not None:
    pts = prepared.x0[prepared.mpdp_index]
    field = mpdp.predict(params.mpdp, pts, prepared.mpdp_means,
                         prepared.mpdp_mask)  # (O, Nmax, 3)
    flat = jnp.concatenate([field[o, :c] for o, (_, c) in
                            enumerate(spec.object_ranges)])
  else:
    flat = jnp.ones((prepared.num_particles, 3), prepared.x0.dtype)
  per = means[prepared.driver_object] * flat
  # Rigid objects keep uniform properties (only their mass matters).
  rigid = jnp.asarray(spec.rigid)[prepared.driver_object]
  per = jnp.where(rigid[:, None], means[prepared.driver_object], per)
  nu = jnp.clip(per[:, 1], 0.0, mpdp.NU_MAX)
  return per[:, 0], nu, per[:, 2]


def _mpm_materials(E, nu, rho, prepared: PreparedScene,
                   sim_config: mpm.SimConfig) -> mpm.Materials:
  """Per-driver ``mpm.Materials`` from per-object tables (jit-safe)."""
  spec = prepared.spec
  obj = prepared.driver_object
  model_of_obj = [sim_config.models.index(m) for m in spec.models]
  fields = {}
  for k in mpm.base.FLOAT_FIELDS[3:]:
    table = [dict(ps).get(k, mpm.MODEL_DEFAULTS[m].get(
      k, mpm.base._GENERIC[k]))  # noqa: SLF001
      for ps, m in zip(spec.object_params, spec.models)]
    fields[k] = jnp.asarray(table, E.dtype)[obj]
  return mpm.Materials(E=E, nu=nu, rho=rho,
                       model_id=jnp.asarray(model_of_obj, jnp.int32)[obj],
                       **fields)


def initial_state(params: Params, prepared: PreparedScene,
                  config: PipelineConfig, field: Array | None = None):
  """``(state, materials, forces, sim_config)`` at frame 0 (pure);
  ``field`` as in :func:`driver_materials`."""
  spec = prepared.spec
  sim_config = make_sim_config(spec, config, prepared.x0.dtype)
  E, nu, rho = driver_materials(params, prepared, config, field)
  materials = _mpm_materials(E, nu, rho, prepared, sim_config)
  v_obj = prepared.frame.vector_to_sim(params.velocity)  # (O, 3)
  v0 = v_obj[prepared.driver_object]
  state = mpm.init_state(prepared.x0, v0, prepared.volume, materials,
                         sim_config, body_id=prepared.body_id)
  # Forces act on whole objects (or ball & object): replace the box/ball
  # selections made by init_state with object masks.
  sel = list(state.bc_data)
  values = list(mpm.make_forces(sim_config, prepared.x0.dtype).values)
  first = len(sim_config.boundary_conditions) - len(config.forces)
  pbc = sim_config.particle_bcs
  for i, (f, oi) in enumerate(zip(config.forces, spec.force_objects)):
    bc_index = first + i
    slot = pbc.index(bc_index)
    in_obj = (prepared.driver_object == oi) if oi >= 0 else jnp.ones(
      prepared.num_particles, bool)
    if f.kind == 'impulse':
      mask = in_obj
    else:
      d = prepared.x0 - jnp.asarray(spec.force_points[i], prepared.x0.dtype)
      mask = in_obj & (jnp.sum(d * d, 1) < f.radius**2)
    sel[slot] = mask.astype(sel[slot].dtype)
    m_sel = jnp.sum(jnp.where(mask, state.mass, 0.0))
    vec = prepared.frame.vector_to_sim(params.forces[i])
    if f.kind == 'impulse':  # velocity change spread over one frame
      values[bc_index] = vec * m_sel / config.frame_dt
    else:  # acceleration of every selected particle
      values[bc_index] = vec * m_sel
  state = state.replace(bc_data=tuple(sel))
  return state, materials, mpm.Forces(values=tuple(values)), sim_config


def deformed_gaussians(prepared: PreparedScene, config: PipelineConfig,
                       x: Array, F: Array | None = None):
  """Simulated Gaussians of one frame, in scene coordinates.

  Args:
    prepared: the prepared scene.
    config: static settings (``use_driver_F``).
    x: (N, 3) driver positions [m, simulation frame].
    F: (N, 3, 3) driver deformation gradients (used with ``use_driver_F``).

  Returns:
    (means (Ks, 3), covariances (Ks, 3, 3), rotations (Ks, 3, 3)).
  """
  dF = F if config.use_driver_F else None
  means, covs, rots = deform_lib.deform(
    prepared.binding, (prepared.rest_means, prepared.rest_covs), x, dF)
  fr = prepared.frame
  return (fr.to_scene(means), fr.covariance_to_scene(covs),
          fr.rotation_to_scene(rots))


def render_frame(prepared: PreparedScene, config: PipelineConfig, means,
                 covs, rots, differentiable: bool = False,
                 render_config: raster.RenderConfig | None = None):
  """Renders the whole scene with the simulated rows replaced (pure)."""
  g_all, covs_all, rots_all = _assemble_scene(prepared, means, covs, rots)
  fn = raster.render_differentiable if differentiable else raster.render
  return fn(g_all, prepared.camera, background=prepared.background,
            covariances=covs_all, view_rotations=rots_all,
            config=render_config or config.render_config)


def simulate(params: Params, prepared: PreparedScene,
             config: PipelineConfig, field: Array | None = None
             ) -> Trajectory:
  """MPDP -> materials -> MLS-MPM rollout -> deformed Gaussians -> frames.

  Pure and jit-able (``simulate_jit``); differentiable with respect to
  ``params`` (use ``config.render='differentiable'`` for gradients through
  the images, or ``'none'`` to stop at the Gaussians).

  Args:
    params: :class:`Params` (e.g. :func:`init_params`).
    prepared: from :func:`prepare_scene`.
    config: the static config ``prepare_scene`` used.
    field: optional (N, 3) per-driver multipliers of (E, nu, rho) that
      replace the MPDP prediction (see :func:`driver_materials`).

  Returns:
    :class:`Trajectory` with ``config.num_frames + 1`` frames.
  """
  state, materials, forces, sim_config = initial_state(params, prepared,
                                                       config, field)
  _, xs, Fs = mpm.rollout(state, materials, forces, sim_config,
                          config.num_frames)
  per_frame = jax.vmap(lambda x, F: deformed_gaussians(prepared, config, x, F))
  means, covs, rots = per_frame(xs, Fs)
  images = overflow = None
  if config.render != 'none':
    diff = config.render == 'differentiable'
    outs = jax.lax.map(
      lambda a: render_frame(prepared, config, *a, differentiable=diff),
      (means, covs, rots))
    images, overflow = outs.image, outs.overflow
  x_scene = prepared.frame.to_scene(xs)
  return Trajectory(x=x_scene, means=means, covariances=covs, rotations=rots,
                    images=images, render_overflow=overflow,
                    materials=(materials.E, materials.nu, materials.rho))


simulate_jit = jax.jit(simulate, static_argnames=('config',))


# ------------------------------------------------------------------ host loop


@dataclasses.dataclass
class RunOutput:
  """Result of :func:`run` (NumPy, scene coordinates).

  Attributes:
    gaussian_positions: (T+1, Ks, 3) float32 centres of the simulated
      Gaussians.
    sim_rows: (Ks,) their row numbers in ``scene.gaussians``.
    particle_positions: (T+1, N, 3) float32 driving particles.
    times: (T+1,) [s].
    files: what was written ('video', 'frames', 'ply', ...) -> path.
    timings: seconds per stage ('compile', 'simulate', 'deform', 'render',
      'write', 'total').
    particle_substeps_per_s: MPM throughput over the run.
  """

  gaussian_positions: np.ndarray
  sim_rows: np.ndarray
  particle_positions: np.ndarray
  times: np.ndarray
  files: dict
  timings: dict
  particle_substeps_per_s: float


def run(
  params: Params,
  prepared: PreparedScene,
  config: PipelineConfig,
  *,
  out_dir: str | None = None,
  video: bool = True,
  png: bool = True,
  ply: bool = False,
  on_frame=None,
) -> RunOutput:
  """Host loop: simulate frame by frame, streaming frames to ``out_dir``.

  One jitted MPM frame per call (``mpm.run``: per-frame stability checks
  that stop with the frame and the fix), then the Gaussians are deformed and
  rendered (re-sizing the rasterizer's capacity on overflow, never dropping
  Gaussians) and written: ``video.mp4`` (GIF fallback), ``frames/``
  (PNG), ``ply/frame_%04d.ply`` (deformed Gaussians, optional). Logs one
  progress line per frame.

  Args:
    params: :class:`Params`.
    prepared: from :func:`prepare_scene`.
    config: the same static config.
    out_dir: output directory, or None to write nothing.
    video, png, ply: which outputs to write.
    on_frame: optional ``callback(frame, means, image)`` (scene
      coordinates; image None with ``render='none'``).

  Returns:
    :class:`RunOutput`.

  Raises:
    physsplat_jax.mpm.SimulationError: the simulation blew up (names the
      frame and the fix); outputs written so far are kept and closed.
  """
  import os
  import time

  from physsplat_jax.io import video as video_lib

  t_start = time.perf_counter()
  timings = dict(compile=0.0, simulate=0.0, deform=0.0, render=0.0,
                 write=0.0)
  t0 = time.perf_counter()
  sim_config = make_sim_config(prepared.spec, config, prepared.x0.dtype)
  state, materials, forces = jax.jit(
    lambda p, pr: initial_state(p, pr, config)[:3])(params, prepared)
  deform_jit = jax.jit(deformed_gaussians, static_argnames='config')
  assemble = jax.jit(_assemble_scene)
  timings['compile'] += time.perf_counter() - t0
  files = {}
  writers = []
  vw = pw = None
  ply_dir = None
  do_render = config.render != 'none'
  if out_dir is not None:
    os.makedirs(out_dir, exist_ok=True)
    if video and do_render:
      vw = video_lib.VideoWriter(os.path.join(out_dir, 'video.mp4'),
                                 fps=config.fps)
      writers.append(vw)
    if png and do_render:
      pw = video_lib.PngFrameWriter(os.path.join(out_dir, 'frames'))
      writers.append(pw)
      files['frames'] = os.path.join(out_dir, 'frames')
    if ply:
      ply_dir = os.path.join(out_dir, 'ply')
      os.makedirs(ply_dir, exist_ok=True)
      files['ply'] = ply_dir
  g_pos = []
  rcfg = [config.render_config]
  num = config.num_frames

  def frame_cb(f, st):
    t1 = time.perf_counter()
    means, covs, rots = deform_jit(prepared, config, st.x, st.F)
    means.block_until_ready()
    timings['deform'] += time.perf_counter() - t1
    g_pos.append(np.asarray(means, np.float32))
    image = None
    if do_render:
      t2 = time.perf_counter()
      g_all, covs_all, rots_all = assemble(prepared, means, covs, rots)
      out = raster.render_image(
        g_all, prepared.camera, background=prepared.background,
        covariances=covs_all, view_rotations=rots_all, config=rcfg[0])
      if out.num_intersections > rcfg[0].resolved_capacity(g_all.num):
        rcfg[0] = dataclasses.replace(
          rcfg[0], capacity=raster._next_capacity(  # noqa: SLF001
            int(out.num_intersections)))
      image = np.clip(out.image, 0.0, 1.0)
      timings['render'] += time.perf_counter() - t2
    t3 = time.perf_counter()
    if vw is not None:
      vw.append(image)
    if pw is not None:
      pw.append(image)
    if ply_dir is not None:
      _write_ply_frame(os.path.join(ply_dir, f'frame_{f:04d}.ply'),
                       prepared, means, covs, rots)
    timings['write'] += time.perf_counter() - t3
    if on_frame is not None:
      on_frame(f, np.asarray(means), image)
    if f > 0:
      logging.info('frame %d/%d: deform+render+write %.2f s', f, num,
                   time.perf_counter() - t1)

  try:
    res = mpm.run(state, materials, forces, sim_config, num,
                  on_frame=frame_cb, keep_positions=True)
  finally:
    for w in writers:
      w.close()
  if vw is not None:
    files['video'] = vw.path
  timings['compile'] += res.compile_s
  timings['simulate'] = res.run_s
  timings['total'] = time.perf_counter() - t_start
  fr = prepared.frame
  x_scene = np.asarray(fr.to_scene(jnp.asarray(res.positions)), np.float32)
  out = RunOutput(
    gaussian_positions=np.stack(g_pos), sim_rows=np.asarray(prepared.sim_rows),
    particle_positions=x_scene, times=res.times, files=files,
    timings=timings, particle_substeps_per_s=res.substeps_per_s)
  if out_dir is not None:
    files['trajectory'] = os.path.join(out_dir, 'trajectory.npz')
    save_trajectory(files['trajectory'], out)
  return out


def save_trajectory(path: str, out: RunOutput) -> None:
  """Writes ``trajectory.npz``: ``x`` float32 (T+1, Ks, 3) positions of the
  simulated Gaussians in the input scene's coordinates (frame 0 = initial),
  ``ids`` (Ks,) their row numbers in the input, ``t`` (T+1,) seconds, and
  ``particles`` (T+1, N, 3) the driving particles."""
  np.savez_compressed(
    path, x=out.gaussian_positions.astype(np.float32),
    ids=out.sim_rows.astype(np.int64), t=np.asarray(out.times, np.float64),
    particles=out.particle_positions.astype(np.float32))


def _assemble_scene(prepared: PreparedScene, means, covs, rots):
  """All Gaussians with the simulated rows replaced (means, covs, rots)."""
  g = prepared.gaussians
  rows = prepared.sim_rows
  dt = g.means.dtype
  all_means = g.means.at[rows].set(means.astype(dt))
  all_covs = g.covariances.at[rows].set(covs.astype(dt))
  eye = jnp.broadcast_to(jnp.eye(3, dtype=dt), all_covs.shape)
  all_rots = eye.at[rows].set(rots.astype(dt))
  return g.replace(means=all_means), all_covs, all_rots


def _write_ply_frame(path, prepared: PreparedScene, means, covs, rots):
  """One deformed frame as an INRIA PLY (every Gaussian of the scene)."""
  from physsplat_jax.io import export as export_lib

  g_all, covs_all, rots_all = _assemble_scene(prepared, means, covs, rots)
  export_lib.save_deformed_ply(path, prepared.gaussians, g_all.means,
                               covs_all, rots_all)


# ------------------------------------------------------------- whole scene


def config_from_dict(d) -> PipelineConfig:
  """A :class:`PipelineConfig` from a dict / ConfigDict (lists -> tuples).

  ``forces`` is a list of dicts with :class:`ForceSpec` fields;
  ``initial_velocity`` a list of ``(name, (vx, vy, vz))`` pairs or a dict
  name -> velocity. Unknown keys raise :class:`PipelineError`.
  """
  d = dict(d.to_dict() if hasattr(d, 'to_dict') else d)
  fields = {f.name: f for f in dataclasses.fields(PipelineConfig)}
  unknown = sorted(set(d) - set(fields))
  if unknown:
    raise PipelineError(f'unknown pipeline config fields {unknown}; valid: '
                        f'{sorted(fields)}')
  if 'forces' in d:
    fs = []
    for i, f in enumerate(d['forces'] or ()):
      if isinstance(f, ForceSpec):
        fs.append(f)
        continue
      f = dict(f)
      bad = sorted(set(f) - {x.name for x in dataclasses.fields(ForceSpec)})
      if bad:
        raise PipelineError(f'forces[{i}] has unknown fields {bad}')
      for k in ('vector', 'point'):
        if f.get(k) is not None:
          f[k] = tuple(float(v) for v in f[k])
      fs.append(ForceSpec(**f))
    d['forces'] = tuple(fs)
  if 'initial_velocity' in d:
    iv = d['initial_velocity'] or ()
    items = iv.items() if isinstance(iv, dict) else iv
    d['initial_velocity'] = tuple(
      (str(n), tuple(float(c) for c in v)) for n, v in items)
  for k in ('background',):
    if k in d:
      d[k] = tuple(float(v) for v in d[k])
  if isinstance(d.get('render_config'), dict):
    d['render_config'] = raster.RenderConfig(**d['render_config'])
  return PipelineConfig(**d)


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


def simulate_scene(
  scene: Scene,
  config: PipelineConfig,
  out_dir: str | None = None,
  *,
  materials: Sequence[Any] | None = None,
  perception_options: Any = None,
  ply: bool = False,
  extra_report: dict | None = None,
) -> tuple[RunOutput, dict]:
  """The whole job on one scene: perceive, prepare, simulate, write.

  Args:
    scene: the scene (``physsplat_jax.load_scene``).
    config: pipeline settings.
    out_dir: where ``video.mp4``, ``frames/``, ``trajectory.npz``,
      ``report.json`` (and ``ply/``) go; None writes nothing.
    materials: one material per object; None runs perception
      (``physsplat_jax.perception.perceive_scene`` with
      ``perception_options``; offline library by default).
    perception_options: ``perception.PerceptionOptions``.
    ply: also write per-frame PLY files.
    extra_report: merged into ``report.json`` (e.g. the command line).

  Returns:
    (:class:`RunOutput`, the report dict).
  """
  import json
  import os
  import time

  from physsplat_jax import perception

  t0 = time.perf_counter()
  if materials is None:
    materials = perception.perceive_scene(scene, perception_options)
  t_perc = time.perf_counter() - t0
  t1 = time.perf_counter()
  prepared, prep = prepare_scene(scene, materials, config)
  params = init_params(prepared, config)
  t_prep = time.perf_counter() - t1
  out = run(params, prepared, config, out_dir=out_dir, ply=ply)
  stages = {'perception': t_perc, 'prepare': t_prep,
            **{f'prepare.{k[:-2]}': v for k, v in prep.timings.items()},
            **out.timings}
  stages['total'] = time.perf_counter() - t0
  objects = []
  for o, m in zip(prep.objects, materials):
    d = m.to_dict() if hasattr(m, 'to_dict') else dataclasses.asdict(m)
    objects.append({**o, 'material': d})
  report = dict(
    scene=scene.name, num_frames=config.num_frames, fps=config.fps,
    objects=objects, colliders=prep.colliders,
    num_gaussians=prep.num_gaussians,
    num_simulated_gaussians=prep.num_simulated_gaussians,
    num_candidates=prep.num_candidates, num_particles=prep.num_particles,
    grid=prep.grid, time_step=prep.time_step,
    particle_substeps_per_s=out.particle_substeps_per_s,
    stage_seconds={k: round(v, 3) for k, v in stages.items()},
    files=out.files, devices=[str(d) for d in jax.devices()],
    jax_version=jax.__version__, config=_jsonable(dataclasses.asdict(config)),
    **(extra_report or {}))
  if out_dir is not None:
    path = os.path.join(out_dir, 'report.json')
    with open(path, 'w') as f:
      json.dump(_jsonable(report), f, indent=1)
    out.files['report'] = path
    report['files'] = dict(out.files)
  return out, report


def summary(report: dict) -> str:
  """A short human summary of a :func:`simulate_scene` report."""
  st = report['stage_seconds']
  total = max(st.get('total', 0.0), 1e-9)
  main = ['perception', 'prepare', 'compile', 'simulate', 'deform', 'render',
          'write']
  parts = ', '.join(f'{k} {st.get(k, 0.0):.1f} s ({100 * st.get(k, 0.0) / total:.0f}%)'
                    for k in main if k in st)
  lines = [
    f'{report["scene"]}: {report["num_frames"]} frames, '
    f'{report["num_particles"]} particles driving '
    f'{report["num_simulated_gaussians"]} of {report["num_gaussians"]} '
    f'Gaussians, {report["time_step"]["substeps_per_frame"]} substeps/frame, '
    f'{report["particle_substeps_per_s"] / 1e6:.2f} M particle-substeps/s',
    f'time {total:.1f} s: {parts}',
  ]
  for f, p in sorted(report.get('files', {}).items()):
    lines.append(f'  {f}: {p}')
  return '\n'.join(lines)


def _jsonable(x):
  if isinstance(x, dict):
    return {str(k): _jsonable(v) for k, v in x.items()}
  if isinstance(x, (list, tuple)):
    return [_jsonable(v) for v in x]
  if isinstance(x, (np.floating, np.integer)):
    return x.item()
  if isinstance(x, np.ndarray):
    return x.tolist()
  if isinstance(x, float) and not math.isfinite(x):
    return str(x)
  return x
