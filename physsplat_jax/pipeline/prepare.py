"""Host-side preparation: a scene and its materials -> a :class:`PreparedScene`.

``prepare_scene(key, scene, materials, config)`` is a composition of named
stages, each a short function of the previous stages' results:

  check      inputs finite and consistent, before any expensive work
  frame      scene -> simulation frame; grid side and corner; colliders
  candidates surface Gaussians + interior fill (``sampling``)
  drivers    driving particles (PGAS / uniform / k-means)
  binding    every simulated Gaussian -> its k nearest drivers (``deform``)
  mpdp       per-object driver gathers; the MPDP field, evaluated once
  time step  substeps per frame from the stiffest point, the initial speeds
             and the impulses
  forces     force targets and ball centres in the simulation frame

Nothing here is traced or differentiated; ``simulate`` is the pure part.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from absl import logging

from physsplat_jax import deform as deform_lib
from physsplat_jax import mpdp
from physsplat_jax import program_store
from physsplat_jax import sampling
from physsplat_jax import struct
from physsplat_jax.mpm.timestep import bucket_substeps as bucket_substeps
from physsplat_jax.pipeline import capture as capture_lib
from physsplat_jax.pipeline import frames as frames_lib
from physsplat_jax.pipeline.colliders import Colliders
from physsplat_jax.pipeline.colliders import find_colliders
from physsplat_jax.pipeline.config import ForceKind
from physsplat_jax.pipeline.config import Ground
from physsplat_jax.pipeline.config import PipelineConfig
from physsplat_jax.pipeline.config import PipelineError
from physsplat_jax.pipeline.config import PrepareConfig
from physsplat_jax.pipeline.config import Sampling
from physsplat_jax.pipeline.config import as_prepare_config
from physsplat_jax.pipeline.frames import SimFrame
from physsplat_jax.pipeline.substeps import given_speed as given_speed
from physsplat_jax.pipeline.substeps import time_step_stage
from physsplat_jax.pipeline.substeps import viscous_dt
from physsplat_jax.types import Array
from physsplat_jax.types import Camera
from physsplat_jax.types import DataError
from physsplat_jax.types import Gaussians
from physsplat_jax.types import Scene
from physsplat_jax.types import check_gaussians
from physsplat_jax.types import device_array


class Params(struct.PyTreeNode):
  """Differentiable inputs of ``simulate`` (all leaves are arrays).

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

  def astype(self, dtype) -> Params:
    """Floating leaves (MPDP weights too) cast (``struct.cast_floats``)."""
    return struct.cast_floats(self, dtype)


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
    force_placements: per force, its ``ForceSpec.placement()`` (object and
      point as given), for ``simulate``'s check of its config.
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
  force_placements: tuple[tuple, ...] = ()

  @property
  def dx(self) -> float:
    return self.grid_size / self.grid_res

  @property
  def frame_dt(self) -> float:
    return self.dt * self.substeps_per_frame


class PreparedScene(struct.PyTreeNode):
  """Everything ``simulate`` needs that is not differentiated.

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
    field: (N, 3) the MPDP field (E, nu, rho multipliers) evaluated once
      at preparation with the params it was given (ones without MPDP);
      pass it as ``simulate(..., field=prepared.field)`` to reuse it.
    means: (O, 3) perceived mean (E [Pa], nu, rho [kg/m^3]).
    frame: scene -> simulation map.
    camera: the rendering camera (scene coordinates) of frame 0.
    orbit: how it turns during the video (``camera_path``; see
      :func:`physsplat_jax.pipeline.capture.frame_camera`).
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
  field: Array
  means: Array
  frame: SimFrame
  camera: Camera
  orbit: capture_lib.CameraOrbit
  background: Array
  spec: SimSpec = struct.field(pytree_node=False)

  @property
  def num_particles(self) -> int:
    return self.x0.shape[0]

  @property
  def num_objects(self) -> int:
    return self.means.shape[0]

  def astype(self, dtype) -> PreparedScene:
    """Floating arrays cast, indices kept (float64: docs/pipeline.md)."""
    return struct.cast_floats(self, dtype)


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
  capture: dict = dataclasses.field(default_factory=dict)


# ------------------------------------------------------------------ stages


def _as_key(key):
  """A PRNG key from a key or an integer seed; else a PipelineError."""
  if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
    return jax.random.PRNGKey(int(key))
  ok = isinstance(key, jax.core.Tracer) or (
    hasattr(key, 'dtype') and (jax.dtypes.issubdtype(
      key.dtype, jax.dtypes.prng_key) or (
        np.shape(key) == (2,) and key.dtype == np.uint32)))
  if not ok:
    raise PipelineError(
      f'prepare_scene: key {key!r} is not a PRNG key; pass '
      'jax.random.PRNGKey(seed) (or an integer seed)')
  return key


def check_inputs(scene: Scene, materials: Sequence[Any]
                 ) -> tuple[list[int], list[int]]:
  """(movable, fixed) object indices; raises on anything unusable."""
  if not isinstance(scene, Scene):
    raise PipelineError(
      f'scene must be a physsplat_jax.Scene, got {type(scene).__name__} '
      f'{scene!r:.60}; load one first: physsplat_jax.load_scene(name or '
      'path) (a built-in scene or a 3DGS PLY)')
  names = [o.name for o in scene.objects]
  if isinstance(materials, (dict, str)) or not hasattr(materials, '__len__'):
    raise PipelineError(
      f'materials must be a sequence with one material per object, in '
      f'scene.objects order (e.g. perception.perceive_scene(scene)); got '
      f'{type(materials).__name__}')
  if len(materials) != len(scene.objects):
    raise PipelineError(
      f'{len(materials)} materials for {len(scene.objects)} objects of scene '
      f'{scene.name!r}; give one material per object (in scene.objects '
      'order).')
  if scene.gaussians.num == 0:
    raise PipelineError(f'scene {scene.name!r} has no Gaussians; load a '
                        'scene with at least one.')
  K = check_gaussians(scene.gaussians, f'scene {scene.name!r}')
  ids = np.asarray(scene.object_ids)
  if ids.shape != (K,) or not np.issubdtype(ids.dtype, np.integer):
    raise DataError(
      f'scene {scene.name!r}: object_ids has shape {ids.shape} and dtype '
      f'{ids.dtype}; expected ({K},) integers, one object index per Gaussian '
      '(-1 for background)')
  out = (ids < -1) | (ids >= len(scene.objects))
  if out.any():
    raise DataError(
      f'scene {scene.name!r}: {int(out.sum())} object_ids are outside -1..'
      f'{len(scene.objects) - 1} (e.g. {int(ids[out][0])}), but the scene has '
      f'{len(scene.objects)} objects; give each Gaussian the index of its '
      'object in scene.objects, or -1')
  try:
    mpu = float(scene.meters_per_unit)
  except (TypeError, ValueError):
    mpu = math.nan
  if not (np.isfinite(mpu) and mpu > 0):
    raise DataError(
      f'scene {scene.name!r}: meters_per_unit={scene.meters_per_unit!r} must '
      'be a positive number (metres per scene unit)')
  movable, fixed = [], []
  for o, info in enumerate(scene.objects):
    if np.any(ids == o):
      (fixed if info.fixed else movable).append(o)
    elif not info.fixed:  # (was dropped silently: Params rows shifted)
      raise PipelineError(
        f'movable object {info.name!r} (scene {scene.name!r}) has no '
        'Gaussians; remove it and its material, mark it fixed, or fix its '
        'segmentation (an empty box, a mask that selects no Gaussian).')
  if not movable:
    raise PipelineError(f'scene {scene.name!r} has no movable object; clear '
                        'ObjectInfo.fixed on the objects that should move.')
  means = np.asarray(scene.gaussians.means)
  for o in movable:
    _check_material(names[o], materials[o])
    ext = np.ptp(means[ids == o], axis=0)
    if float(np.max(ext)) <= 0:
      raise PipelineError(
        f'object {names[o]!r} has zero extent (all of its '
        f'{int(np.sum(ids == o))} Gaussians at one point); a simulated '
        'object needs a volume: mark it fixed or use a real scene.')
  return movable, fixed


def _check_material(name: str, m) -> None:
  if not all(hasattr(m, f) for f in ('model', 'E', 'nu', 'rho')):
    raise PipelineError(
      f'object {name!r}: material {m!r} is not a material; give a '
      'pipeline.ObjectMaterial (or a perception result)')
  bad = []
  if not (np.isfinite(m.E) and m.E > 0):
    bad.append(f'E={m.E!r} (use > 0 Pa)')
  if not (np.isfinite(m.nu) and 0 <= m.nu < 0.5):
    bad.append(f'nu={m.nu!r} (use 0 <= nu < 0.5)')
  if not (np.isfinite(m.rho) and m.rho > 0):
    bad.append(f'rho={m.rho!r} (use > 0 kg/m^3)')
  if bad:
    raise PipelineError(f'object {name!r}: bad material ' + ', '.join(bad))


@dataclasses.dataclass
class _Frame:
  """Output of the frame stage."""

  frame: SimFrame
  L: float
  dx: float
  colliders: Colliders
  rows: np.ndarray  # scene rows of the movable Gaussians
  local_ids: np.ndarray  # their movable-object index
  g_sim: Gaussians  # movable Gaussians in the simulation frame


def _quantise(v) -> tuple[float, ...]:
  return tuple(round(float(c), 7) for c in v)


def motion_reach(lo, hi, velocities, gravity: float):
  """The box the movable objects can reach when launched (simulation frame).

  Each velocity (initial velocities and impulses, [m/s], +z up) is followed
  ballistically: up to ``v_z^2 / 2g`` above the top, and sideways over the
  flight time back down to the lowest point, ``v_h (v_z + sqrt(v_z^2 +
  2 g h)) / g``. Without gravity nothing bounds the flight: the reach is one
  second of travel.

  Returns:
    (lo, hi) of the union of the rest box and the reach.
  """
  lo, hi = np.array(lo, np.float64), np.array(hi, np.float64)
  h = float(hi[2] - lo[2])
  for v in velocities:
    v = np.asarray(v, np.float64)
    up = max(float(v[2]), 0.0)
    if gravity > 0:
      t = (up + math.sqrt(up * up + 2 * gravity * h)) / gravity
      top = up * up / (2 * gravity)
    else:
      t, top = 1.0, up
    travel = v * t
    travel[2] = top
    lo = np.minimum(lo, lo + np.minimum(travel, 0.0))
    hi = np.maximum(hi, hi + np.maximum(travel, 0.0))
  return lo, hi


def _given_ground(z: float, lowest: float, dx: float) -> float:
  if z > lowest + dx:
    raise PipelineError(
      f'ground_height puts the ground at z={z:.4g} m, above the lowest '
      f'simulated Gaussian (z={lowest:.4g} m, scene up axis, metres): lower '
      'ground_height, or leave the floor out of the simulation (roi, '
      'fixed objects).')
  return z


def _warn_unresolved(x_rs, ids, movable, names, L, dx, extent, cfg) -> None:
  """Warns about movable objects less than two cells across: the grid
  cannot resolve them (a launch speed that grows the grid to hold the
  flight is the usual cause), and their motion is mostly numerical."""
  for o in movable:
    size = float(np.max(np.ptp(x_rs[ids == o], axis=0)))
    if size >= 2 * dx:
      continue
    grown = L > 1.01 * extent * (1 + 2 * cfg.margin)
    why = (f'the grid grew to {L:.3g} m to hold the launched motion '
           '(initial_velocity, impulses): lower those speeds or raise '
           'grid_res' if grown else 'raise grid_res or lower margin')
    logging.warning(
      'object %r is %.3g m across, %.2g cells of %.3g m: too small for the '
      'grid to resolve, so its motion will be mostly numerical; %s.',
      names[o], size, size / dx, dx, why)


def sim_frame_stage(scene: Scene, movable, fixed, cfg: PrepareConfig,
                    gravity: float = 9.8) -> _Frame:
  """Simulation frame, grid (side, corner) and colliders.

  The grid is a cube around the movable objects with ``cfg.margin`` of
  their size on each side, grown to hold where their initial velocities
  and impulses can take them (:func:`motion_reach`).
  """
  ids = np.asarray(scene.object_ids)
  names = [o.name for o in scene.objects]
  R = frames_lib.up_rotation(scene.up_vector)
  s = float(scene.meters_per_unit)
  x_rs = s * np.asarray(scene.gaussians.means, np.float64) @ R.T
  mov_mask = np.isin(ids, movable)
  lo, hi = x_rs[mov_mask].min(0), x_rs[mov_mask].max(0)
  ext = hi - lo
  kicks = [v for _, v in cfg.initial_velocity] + [
    f.vector for f in cfg.forces if f.kind == 'impulse']
  lo, hi = motion_reach(lo, hi, [R @ np.asarray(v) for v in kicks], gravity)
  L = max(float(np.max(ext)) * (1 + 2 * cfg.margin),
          float(np.max(hi - lo)) * (1 + 2 * min(cfg.margin, 0.1)))
  # Sideways, at least 4 cells (fewer on a grid under 32) between the reach
  # and each wall: the domain box's 3-cell border holds anything nearer (a
  # launch that set L by its reach left 2.7 cells on a 32-cell grid, and the
  # objects started in the border on the side away from the motion).
  room = 2 * min(4.0, cfg.grid_res / 8) / cfg.grid_res
  L = max(L, float(np.max((hi - lo)[:2])) / (1 - room))
  zlo = lo[2]
  for _ in range(2):  # the support may sit under the objects: find it
    for _ in range(2):  # vertical room: 4 cells below, 4 above
      L = max(L, float(hi[2] - zlo) + 8 * L / cfg.grid_res)
    # Static values are quantised (grid side to 6 significant digits,
    # positions to 0.1 um) so equal geometry gives an equal SimSpec, i.e.
    # one compilation, whatever the rounding of the input coordinates.
    L = float(f'{L:.6g}')
    dx = L / cfg.grid_res
    colliders = find_colliders(x_rs, ids, movable, fixed, names, tol=dx)
    ground = colliders.ground_z
    if cfg.ground_height is not None:
      ground = _given_ground(cfg.ground_height * s, lo[2], dx)
      colliders = dataclasses.replace(colliders, ground_z=ground, notes=(
        f'ground plane set by ground_height={cfg.ground_height} '
        f'(z={ground:.4f} m)',) + tuple(
          n for n in colliders.notes if 'ground plane' not in n))
    if cfg.ground is not Ground.NONE:
      zlo = min(lo[2], ground)
  # With a ground the grid floor sits 4 cells under it (3 boundary cells);
  # without one the objects may fall, so the grid is centred on them.
  if cfg.ground is Ground.NONE:
    z0 = 0.5 * (lo[2] + hi[2]) - L / 2
  else:
    z0 = min(lo[2], ground) - 4 * dx
  lower = np.array([0.5 * (lo[0] + hi[0]) - L / 2,
                    0.5 * (lo[1] + hi[1]) - L / 2, z0])
  shift = -lower
  # With ground='none' the plane is unused: keep it out of the static spec
  # so scenes that differ only in their lowest point compile once.
  colliders = dataclasses.replace(
    colliders, ground_z=(None if cfg.ground is Ground.NONE
                         else round(float(ground + shift[2]), 7)),
    anchors=tuple((_quantise(np.add(a, shift)), _quantise(np.add(b, shift)))
                  for a, b in colliders.anchors))
  frame = SimFrame(rotation=device_array(R, jnp.float32),
                   scale=device_array(s, jnp.float32),
                   shift=device_array(shift, jnp.float32))
  _warn_unresolved(x_rs, ids, movable, names, L, dx, float(np.max(ext)), cfg)
  rows = np.nonzero(mov_mask)[0]
  local = {o: i for i, o in enumerate(movable)}
  local_ids = np.array([local[o] for o in ids[rows]], np.int32)
  g_sim = frames_lib.transform_gaussians(scene.gaussians.subset(rows), frame)
  return _Frame(frame, L, dx, colliders, rows, local_ids, g_sim)


def candidates_stage(key, fr: _Frame, num_movable: int, cfg: PrepareConfig):
  """Candidate particles: surface Gaussians plus interior fill."""
  means = np.asarray(fr.g_sim.means)
  obj_ext = max(float(np.max(np.ptp(means[fr.local_ids == i], axis=0)))
                for i in range(num_movable))
  # Fill cells of half an MPM cell over the largest object, plus margins.
  margin = sampling.FillConfig().margin_cells
  fill_res = int(np.clip(math.ceil(obj_ext / (0.5 * fr.dx)) + 2 * margin,
                         16, 128))
  return sampling.make_candidates(
    key, fr.g_sim, fr.local_ids, fill=cfg.fill,
    fill_config=sampling.FillConfig(grid_res=fill_res))


def drivers_stage(key, cand, mats, names, dx: float, cfg: PrepareConfig):
  """Driving particles sorted by object: (x0, volume, object, counts)."""
  if cfg.max_particles >= len(cand.x):
    logging.info('max_particles=%d >= %d candidates: every candidate is a '
                 'driving particle (no sampling)', cfg.max_particles,
                 len(cand.x))
  if cfg.sampling is Sampling.KMEANS:
    drv = sampling.select_drivers(key, cand, 'kmeans',
                                  budget=min(cfg.max_particles, len(cand.x)))
  else:
    base_r = dx * (1.24 / cfg.particles_per_cell) ** (1.0 / 3.0)
    E_obj = {i: (1e12 if m.rigid else float(m.E)) for i, m in enumerate(mats)}
    drv = sampling.select_drivers(
      key, cand, cfg.sampling.value, E=E_obj,
      config=sampling.PGASConfig(base_radius=base_r),
      budget=cfg.max_particles)
  order = np.argsort(drv.object_ids, kind='stable')
  dobj = drv.object_ids[order].astype(np.int32)
  counts = np.bincount(dobj, minlength=len(mats))
  need = max(cfg.bind_k, 8)
  for i, name in enumerate(names):
    if counts[i] < need:
      raise PipelineError(
        f'object {name!r} got only {counts[i]} driving particles (need '
        f'>= {need}): it is small for the grid (dx = {dx:.4f} m); raise '
        'grid_res, particles_per_cell or max_particles'
        + (f', or lower bind_k (now {cfg.bind_k})' if cfg.bind_k > 8 else '')
        + '.')
  return drv.x[order], drv.volume[order], dobj, counts


def mpdp_stage(x0, dobj, counts, mats, use_mpdp: bool, mpdp_params,
               volume=None):
  """Per-object gathers, condition vectors and the MPDP field (N, 3)
  (with each object's volume-weighted mean 1 when ``volume`` is given)."""
  starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
  nmax = int(counts.max())
  index = np.zeros((len(mats), nmax), np.int32)
  mask = np.zeros((len(mats), nmax), bool)
  for i in range(len(mats)):
    index[i, :counts[i]] = starts[i] + np.arange(counts[i])
    mask[i, :counts[i]] = True
  means = np.stack([
    np.asarray(mpdp.encode_means(m.E, m.nu, m.rho, m.model, m.rigid))
    for m in mats])
  field = np.ones((len(x0), 3), np.float32)
  if use_mpdp:
    params = mpdp.load_pretrained() if mpdp_params is None else mpdp_params
    weights = (np.ones(index.shape, np.float32) if volume is None
               else np.asarray(volume, np.float32)[index])
    args = (params, device_array(x0[index]), device_array(means),
            device_array(mask), device_array(weights))
    # Traced once across processes when a compilation cache is on (1.2 s of
    # Python for the donut's 63k points on the 2-core VM).
    predict = program_store.compile_stored(
      _predict_jit, args, name='mpdp_predict',
      out_tree=jax.tree.structure(0))
    per_obj = np.asarray(predict(*args))
    field = per_obj[mask]  # objects are contiguous in driver order
  return index, mask, means, field


_predict_jit = jax.jit(mpdp.predict)


def forces_stage(cfg: PrepareConfig, frame: SimFrame, x0, dobj, movable_names):
  """(object index per force, ball centre per force [m, simulation])."""
  f_obj, f_pts = [], []
  for f in cfg.forces:
    oi = -1
    if f.object:
      if f.object not in movable_names:
        raise PipelineError(
          f'force on object {f.object!r}: no such movable object; choose '
          f'from {list(movable_names)}')
      oi = list(movable_names).index(f.object)
    f_obj.append(oi)
    sel = dobj == oi if oi >= 0 else np.ones(len(x0), bool)
    if f.point is not None:
      p = np.asarray(frame.to_sim(jnp.asarray(f.point, jnp.float32)))
    else:
      p = x0[sel].mean(0)
    f_pts.append(_quantise(p))
    if f.kind is ForceKind.POINT:
      hit = np.sum(np.sum((x0[sel] - p) ** 2, axis=1) < f.radius ** 2)
      if hit == 0:
        logging.warning(
          'point force on %r: its ball (radius %.3g m around %s) holds none '
          'of the object\'s particles, so it does nothing; move the point '
          'onto the object or widen the radius.', f.object or 'every object',
          f.radius, f.point)
  for name, _ in cfg.initial_velocity:
    if name and name not in movable_names:
      raise PipelineError(
        f'initial_velocity for object {name!r}: no such movable object; '
        f'choose from {list(movable_names)}')
  return tuple(f_obj), tuple(f_pts)


# ------------------------------------------------------------- composition


def start_kernel_check(config) -> bool:
  """On a GPU, with ``constitutive_kernel='auto'`` (a ``PrepareConfig``
  has none: 'auto'), starts the MPM stress kernel's build check in the
  background, so that its compiles (seconds on a cold cache) overlap the
  preparation instead of the frame's compile. Returns whether it did."""
  if (getattr(config, 'constitutive_kernel', 'auto') != 'auto'
      or jax.default_backend() != 'gpu'):
    return False
  from physsplat_jax.mpm import pallas_constitutive  # noqa: PLC0415
  pallas_constitutive.start_probe('float32')  # the prepared scene's dtype
  return True


def prepare_scene(
  key,
  scene: Scene,
  materials: Sequence[Any] | None = None,
  config: PrepareConfig | PipelineConfig = PrepareConfig(),
  mpdp_params: Any = None,
  *,
  gravity: float | None = None,
  use_mpdp: bool | None = None,
) -> tuple[PreparedScene, PrepareReport]:
  """Host-side, non-differentiable preparation of a scene for simulation.

  Args:
    key: PRNG key for filling and sampling (or an integer seed).
    scene: the segmented scene; objects with ``ObjectInfo.fixed`` become
      colliders, the others are simulated.
    materials: one material record (``physsplat_jax.ObjectMaterial``) per
      ``scene.objects`` (fixed objects' entries are only reported).
    config: a :class:`PrepareConfig` (or a :class:`PipelineConfig`).
    mpdp_params: MPDP params whose field is evaluated once here (time step,
      ``PreparedScene.field``); default the shipped pretrained params.
    gravity, use_mpdp: as in the simulate config; default that of a
      ``PipelineConfig``, else 9.8 and True. They only bound the time step.

  Returns:
    (prepared scene, report).

  Raises:
    PipelineError: nothing to simulate, an empty movable object, a bad
      material or key, an object too small for the grid, too few driving
      particles, or over ``max_substeps_per_frame`` substeps per frame.
    DataError: Gaussians, object ids or ``meters_per_unit`` of the wrong
      shape or value (non-finite included), naming the field.
  """
  if isinstance(key, Scene):  # the old order: (scene, materials, config)
    old_mpdp = mpdp_params if isinstance(
      config, (PrepareConfig, PipelineConfig)) else config
    return _prepare_old_order(
      key, scene, PipelineConfig() if materials is None else materials,
      old_mpdp)
  key = _as_key(key)
  if gravity is None:
    gravity = getattr(config, 'gravity', 9.8)
  if use_mpdp is None:
    use_mpdp = getattr(config, 'use_mpdp', True)
  cfg = as_prepare_config(config)
  start_kernel_check(config)
  timings = {}
  t = time.perf_counter()
  movable, fixed = check_inputs(scene, materials)
  scene, capture = capture_lib.filter_scene(scene, cfg)
  names = [o.name for o in scene.objects]
  mov_names = tuple(names[o] for o in movable)
  mats = [materials[o] for o in movable]
  fr = sim_frame_stage(scene, movable, fixed, cfg, gravity)
  timings['frame_s'], t = time.perf_counter() - t, time.perf_counter()
  k_fill, k_drv = jax.random.split(key)
  cand = candidates_stage(k_fill, fr, len(movable), cfg)
  timings['filling_s'], t = time.perf_counter() - t, time.perf_counter()
  x0, vol, dobj, counts = drivers_stage(k_drv, cand, mats, mov_names, fr.dx,
                                        cfg)
  timings['sampling_s'], t = time.perf_counter() - t, time.perf_counter()
  binding = deform_lib.make_binding(
    np.asarray(fr.g_sim.means), x0, k=cfg.bind_k, dtype=np.float32,
    gauss_object_ids=fr.local_ids, driver_object_ids=dobj)
  timings['binding_s'], t = time.perf_counter() - t, time.perf_counter()
  index, mask, cond, field = mpdp_stage(x0, dobj, counts, mats, use_mpdp,
                                        mpdp_params, vol)
  timings['mpdp_s'], t = time.perf_counter() - t, time.perf_counter()
  rigid = tuple(bool(m.rigid or m.model == 'rigid') for m in mats)
  substeps, c_max = time_step_stage(mats, rigid, field, dobj, fr.dx, cfg,
                                    gravity)
  timings['time_step_s'], t = time.perf_counter() - t, time.perf_counter()
  f_obj, f_pts = forces_stage(cfg, fr.frame, x0, dobj, mov_names)
  starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
  spec = SimSpec(
    object_names=mov_names, scene_objects=tuple(movable),
    models=tuple('rigid' if r else m.model for r, m in zip(rigid, mats)),
    rigid=rigid,
    object_params=tuple(tuple(sorted(dict(m.params).items())) for m in mats),
    object_ranges=tuple((int(a), int(c)) for a, c in zip(starts, counts)),
    grid_lower=(0.0, 0.0, 0.0), grid_size=fr.L, grid_res=cfg.grid_res,
    substeps_per_frame=substeps, dt=cfg.frame_dt / substeps,
    colliders=fr.colliders, force_objects=f_obj, force_points=f_pts,
    force_placements=tuple(f.placement() for f in cfg.forces))
  bodies = np.cumsum(rigid) - 1
  body_id = np.where(np.asarray(rigid)[dobj], bodies[dobj], -1)
  f32 = lambda a: device_array(a, jnp.float32)  # noqa: E731
  prepared = PreparedScene(
    gaussians=scene.gaussians, sim_rows=device_array(fr.rows, jnp.int32),
    rest_means=f32(fr.g_sim.means),
    rest_covs=f32(np.asarray(fr.g_sim.covariances)), binding=binding,
    x0=f32(x0), volume=f32(vol), driver_object=device_array(dobj),
    body_id=device_array(body_id, jnp.int32),
    mpdp_index=device_array(index), mpdp_mask=device_array(mask),
    mpdp_means=f32(cond), field=f32(field),
    means=f32([[m.E, m.nu, m.rho] for m in mats]), frame=fr.frame,
    camera=frames_lib.render_camera(scene, cfg),
    orbit=capture_lib.camera_orbit(scene, fr.rows, cfg),
    background=f32(cfg.background), spec=spec)
  report = _report(scene, materials, movable, counts, fr, cand, x0, spec,
                   c_max, cfg, timings)
  report.capture = capture
  dt_visc = viscous_dt(mats, rigid, field, dobj, fr.dx)
  if math.isfinite(dt_visc):  # (a viscous stress's bound, when one binds)
    report.time_step['viscous_dt_s'] = dt_visc
  logging.info('prepared %r: %d particles for %d Gaussians of %d objects, '
               'grid %d^3 (dx %.4f m), %d substeps/frame (dt %.3g s)',
               scene.name, len(x0), len(fr.rows), len(movable), cfg.grid_res,
               fr.dx, substeps, spec.dt)
  return prepared, report


def _report(scene, materials, movable, counts, fr, cand, x0, spec, c_max,
            cfg, timings) -> PrepareReport:
  ids = np.asarray(scene.object_ids)
  local = {o: i for i, o in enumerate(movable)}
  objects = []
  for o, info in enumerate(scene.objects):
    m = materials[o]
    objects.append(dict(
      name=info.name, fixed=bool(info.fixed),
      material=getattr(m, 'material_key', ''), model=getattr(m, 'model', ''),
      E=float(m.E), nu=float(m.nu), rho=float(m.rho), rigid=bool(m.rigid),
      source=getattr(m, 'source', ''), reason=getattr(m, 'reason', ''),
      num_gaussians=int(np.sum(ids == o)),
      num_particles=int(counts[local[o]]) if o in local else 0))
  return PrepareReport(
    objects=objects, colliders=list(fr.colliders.notes),
    num_gaussians=int(scene.gaussians.num),
    num_simulated_gaussians=int(len(fr.rows)),
    num_candidates=int(len(cand.x)), num_particles=int(len(x0)),
    grid=dict(res=cfg.grid_res, size_m=fr.L, dx_m=fr.dx),
    time_step=dict(substeps_per_frame=spec.substeps_per_frame, dt_s=spec.dt,
                   max_wave_speed_m_s=c_max, cfl=cfg.cfl),
    timings=timings)


def _prepare_old_order(scene, materials, config, mpdp_params):
  warnings.warn(
    'prepare_scene(scene, materials, config) is deprecated: pass the PRNG '
    'key first, prepare_scene(key, scene, materials, config) (the old order '
    'used jax.random.PRNGKey(config.seed)); it goes in the next release.',
    DeprecationWarning, stacklevel=3)
  key = jax.random.PRNGKey(getattr(config, 'seed', 0))
  return prepare_scene(key, scene, materials, config, mpdp_params)
