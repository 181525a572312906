"""Pipeline settings: host-side preparation apart from the static jit key.

Three frozen, hashable dataclasses:

- :class:`PrepareConfig`: what :func:`~physsplat_jax.pipeline.prepare_scene`
  reads on the host: grid, sampling, binding, time step, camera. Changing it
  changes the prepared scene, never the compiled ``simulate`` by itself.
- :class:`SimulateConfig`: the small static config of
  :func:`~physsplat_jax.pipeline.simulate` (its jit key): frames, gravity,
  contact, force kinds, rendering mode.
- :class:`PipelineConfig`: both, flat, as scripts and config files write it;
  ``.prepare`` and ``.simulate`` give the two parts. The random key is never
  part of a config: ``prepare_scene(key, ...)`` takes it; ``seed`` here only
  feeds the scripts' key.

Modes are string enums (``Ground.SLIP == 'slip'``), so the strings of
config files keep working.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import math
from typing import Any

import numpy as np
from absl import logging

from physsplat_jax import mpm
from physsplat_jax.errors import PhysSplatError
from physsplat_jax.render import raster
from physsplat_jax.render.config import RenderInputError
from physsplat_jax.render.views import BACKGROUNDS
from physsplat_jax.render.views import parse_background


class PipelineError(PhysSplatError, ValueError):
  """The scene or config cannot be simulated; the message names the fix."""


class Ground(enum.StrEnum):
  """Contact with the support plane."""

  SLIP = 'slip'  # separating, with Coulomb friction
  STICKY = 'sticky'
  NONE = 'none'


class Sampling(enum.StrEnum):
  """How the driving particles are picked from the candidates."""

  PGAS_CVT = 'pgas-cvt'  # PGAS allocation + weighted Lloyd placement
  PGAS = 'pgas'  # PGAS radius, Poisson-disk placement
  UNIFORM = 'uniform'
  KMEANS = 'kmeans'


class RenderMode(enum.StrEnum):
  """What :func:`simulate` renders."""

  FAST = 'fast'  # render-only rasterizer (no gradient through images)
  DIFFERENTIABLE = 'differentiable'
  NONE = 'none'


class CameraPath(enum.StrEnum):
  """How the video camera moves during the simulation."""

  FIXED = 'fixed'
  ORBIT = 'orbit'  # turns orbit_degrees about the up axis over the video


class ForceKind(enum.StrEnum):
  IMPULSE = 'impulse'  # a velocity change applied once, at ``start``
  POINT = 'point'  # a constant acceleration inside a ball over a window


def _enum(cls, value, owner: str, name: str):
  try:
    return cls(value)
  except ValueError:
    raise PipelineError(
      f'{owner}.{name}={value!r} is invalid: use one of '
      f'{[m.value for m in cls]}.') from None


def _finite(value) -> bool:
  try:
    return math.isfinite(float(value))
  except (TypeError, ValueError):
    return False


def _whole(v) -> bool:
  """An integer (not a bool, not 16.5)."""
  return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


@functools.lru_cache(maxsize=64)
def _warn_once(message: str) -> None:
  """A config warning, once per process (configs are rebuilt often)."""
  logging.warning('%s', message)


def _check_types(owner: str, obj) -> None:
  """Every int, float and bool field holds one (``2.5`` frames was
  truncated, ``'9.8'`` a TypeError deep inside the simulation)."""
  for f in dataclasses.fields(obj):
    kind = str(f.type).replace('| None', '').strip()
    optional = '| None' in str(f.type)
    value = getattr(obj, f.name)
    if value is None and optional:
      continue
    real = (isinstance(value, (int, float, np.integer, np.floating))
            and not isinstance(value, (bool, np.bool_)))
    for want, ok, fix in (
        ('int', _whole(value), 'a whole number'),
        ('float', real, 'a number'),
        ('bool', isinstance(value, (bool, np.bool_)) or (
          _whole(value) and value in (0, 1)), 'True or False'),
        ('raster.RenderConfig', isinstance(value, raster.RenderConfig),
         'a physsplat_jax.render.RenderConfig')):
      if kind == want and not ok:
        raise PipelineError(
          f'{owner}.{f.name}={value!r} is invalid: use {fix}'
          f'{" or None" if optional else ""}.')


def _check(owner: str, obj, checks) -> None:
  for ok, name, fix in checks:
    if not ok:
      value = getattr(obj, name.split('/')[0])
      raise PipelineError(f'{owner}.{name}={value!r} is invalid: {fix}.')


@dataclasses.dataclass(frozen=True)
class ForceSpec:
  """A force acting on the simulation (static description).

  Attributes:
    kind: :class:`ForceKind` ('impulse' or 'point', as PhysDreamer's poke).
    object: name of the object it acts on ('' = every movable object).
    vector: (3,) velocity change [m/s] for 'impulse', acceleration [m/s^2]
      for 'point', in the scene's axes; the simulated value is
      ``Params.forces`` (differentiable), initialised from this.
    point: (3,) centre of the ball in scene coordinates (for 'point'); None
      means the object's centre.
    radius: ball radius [m] (for 'point').
    start, end: time window [s].
  """

  kind: ForceKind = ForceKind.IMPULSE
  object: str = ''
  vector: tuple[float, float, float] = (0.0, 0.0, 0.0)
  point: tuple[float, float, float] | None = None
  radius: float = 0.05
  start: float = 0.0
  end: float = 0.0

  def __post_init__(self):
    object.__setattr__(self, 'kind',
                       _enum(ForceKind, self.kind, 'ForceSpec', 'kind'))
    for k in ('vector', 'point'):
      v = getattr(self, k)
      if v is not None and (not isinstance(v, (tuple, list, np.ndarray))
                            or len(v) != 3):
        raise PipelineError(
          f'ForceSpec on {self.object or "every object"!r}: {k}={v!r} must '
          'be three numbers (x, y, z) in scene axes.')
    vals = list(self.vector) + list(self.point or ()) + [
      self.radius, self.start, self.end]
    if not all(_finite(v) for v in vals):
      raise PipelineError(
        f'ForceSpec on {self.object or "every object"!r} has a non-finite '
        f'value (vector={self.vector}, point={self.point}, radius='
        f'{self.radius}, start={self.start}, end={self.end}); give finite '
        'numbers.')
    _check('ForceSpec', self, [
      (self.radius > 0, 'radius', 'use > 0 m'),
      (self.start >= 0, 'start', 'use >= 0 s'),
      (self.kind is ForceKind.IMPULSE or self.end > self.start, 'end',
       'a point force needs end > start [s]'),
    ])

  def placement(self) -> tuple:
    """``(object, point)``: what ``prepare_scene`` places (the particles a
    force selects); the rest is read when simulating."""
    point = None if self.point is None else tuple(float(v) for v in
                                                  self.point)
    return self.object, point

  def window(self, frame_dt: float) -> tuple[float, float]:
    """(start, end) [s]; an impulse acts over the frame after ``start``."""
    if self.kind is ForceKind.IMPULSE:
      return self.start, self.start + frame_dt
    return self.start, self.end


@dataclasses.dataclass(frozen=True)
class PrepareConfig:
  """Host-side settings of :func:`prepare_scene` (not a jit key).

  Attributes:
    fps: frames per second of the output [1/s] (the frame step).
    substeps_per_frame: MPM substeps per frame; None picks them from the
      CFL bound of the stiffest deformable material and the initial and
      impulse speeds (:func:`~physsplat_jax.pipeline.substeps.given_speed`),
      rounded up to 16 steps per octave
      (:func:`~physsplat_jax.mpm.timestep.bucket_substeps`) so that a
      new seed or budget seldom recompiles the simulation (it can at a
      bucket's edge: set the count to loop over keys with one program).
    cfl: Courant number used when choosing substeps.
    max_substeps_per_frame: refuse automatic step counts above this (a run
      that would never end); raise it to allow very stiff materials.
    grid_res: MPM grid cells per axis.
    margin: free space around the movable objects, as a fraction of their
      size, on each side (the grid is a cube).
    ground: :class:`Ground` (places the grid floor under the support).
    sampling: :class:`Sampling` driving-particle method.
    particles_per_cell: target driving particles per grid cell of the
      stiffest material (sets PGAS's base radius).
    max_particles: the number of driving particles (exactly this many
      for 'pgas-cvt' and 'kmeans', at most for the Poisson disks); a scene
      with no more candidates than this simulates every candidate (nothing
      to choose; logged).
    fill: fill object interiors with candidate particles.
    bind_k: drivers per Gaussian for the deformation.
    forces: :class:`ForceSpec` tuple (targets and ball centres resolved).
    initial_velocity: ``((object_name, (vx, vy, vz)), ...)`` [m/s, scene
      axes]; '' as a name means every movable object.
    width, height: rendered frame size [pixels].
    camera_index: which scene camera renders (-1: a fitted default).
    background: RGB in [0, 1], or a name ('white', 'black', 'grey') or
      'r,g,b' string as render's ``--background`` takes.
    camera_path: :class:`CameraPath`: 'fixed', or 'orbit' (the camera turns
      about the scene's up axis through the centre of the simulated
      objects, ``orbit_degrees`` over the whole video).
    orbit_degrees: total turn of an orbit [degrees]; the sign is the
      direction (counter-clockwise seen from above for > 0).
    roi: region of interest ``(xmin, xmax, ymin, ymax, zmin, zmax)`` in
      scene units and axes (PhysGaussian's ``sim_area`` order), or None:
      movable Gaussians outside it stay static in the render and are not
      simulated.
    min_opacity: movable Gaussians of activated opacity below this stay
      static and are not simulated (PhysGaussian's ``opacity_threshold``,
      which removes them from the render too); 0 keeps all.
    ground_height: height of the support plane along the scene's up axis
      [scene units] (``x . up``), or None to find it (the top of a fixed
      support under the movable objects, else their lowest point).
    floater_factor: a movable Gaussian whose 8th-nearest neighbour (within
      its object) is farther than this many times the object's median such
      distance is a floater: it stays static and does not size the grid;
      0 disables the test.
  """

  fps: float = 30.0
  substeps_per_frame: int | None = None
  cfl: float = 0.4
  max_substeps_per_frame: int = 20_000
  grid_res: int = 48
  margin: float = 0.3
  ground: Ground = Ground.SLIP
  sampling: Sampling = Sampling.PGAS_CVT
  particles_per_cell: float = 4.0
  max_particles: int = 40_000
  fill: bool = True
  bind_k: int = 8
  forces: tuple[ForceSpec, ...] = ()
  initial_velocity: tuple[tuple[str, tuple[float, float, float]], ...] = ()
  width: int = 512
  height: int = 384
  camera_index: int = 0
  background: tuple[float, float, float] = (1.0, 1.0, 1.0)
  camera_path: CameraPath = CameraPath.FIXED
  orbit_degrees: float = 360.0
  roi: tuple[float, float, float, float, float, float] | None = None
  min_opacity: float = 0.0
  floater_factor: float = 8.0
  ground_height: float | None = None

  def __post_init__(self):
    if isinstance(self.background, str):  # as render's --background
      try:
        object.__setattr__(self, 'background',
                           parse_background(self.background))
      except RenderInputError:
        pass  # refused below, naming the field
    _check_types('PrepareConfig', self)
    object.__setattr__(self, 'ground',
                       _enum(Ground, self.ground, 'PrepareConfig', 'ground'))
    object.__setattr__(self, 'camera_path', _enum(
      CameraPath, self.camera_path, 'PrepareConfig', 'camera_path'))
    roi = self.roi
    if roi is not None and not (
        len(roi) == 6 and all(_finite(v) for v in roi)
        and all(roi[2 * i] < roi[2 * i + 1] for i in range(3))):
      raise PipelineError(
        f'PrepareConfig.roi={roi!r} is invalid: give six finite numbers '
        '(xmin, xmax, ymin, ymax, zmin, zmax) in scene units with each min '
        'below its max, or None for the whole scene.')
    object.__setattr__(self, 'sampling', _enum(
      Sampling, self.sampling, 'PrepareConfig', 'sampling'))
    _check('PrepareConfig', self, [
      (_finite(self.fps) and self.fps > 0, 'fps', 'use a finite fps > 0'),
      (self.substeps_per_frame is None or self.substeps_per_frame >= 1,
       'substeps_per_frame', 'use >= 1 or None (automatic)'),
      (_finite(self.cfl) and 0 < self.cfl <= 1, 'cfl',
       'use a Courant number in (0, 1]'),
      (self.max_substeps_per_frame >= 1, 'max_substeps_per_frame',
       'use >= 1'),
      (_whole(self.grid_res) and 8 <= self.grid_res <= 512, 'grid_res',
       'use a whole number in 8..512'),
      (_finite(self.margin) and 0 <= self.margin <= 10, 'margin',
       'use a fraction of the objects\' size in [0, 10] (default 0.3)'),
      (_finite(self.particles_per_cell) and self.particles_per_cell > 0,
       'particles_per_cell', 'use > 0'),
      (self.max_particles >= 8, 'max_particles', 'use >= 8'),
      (4 <= self.bind_k <= 64, 'bind_k', 'use 4..64 driving particles per '
       'Gaussian'),
      (_whole(self.width) and self.width >= 1, 'width',
       'use a whole number of pixels >= 1'),
      (_whole(self.height) and self.height >= 1, 'height',
       'use a whole number of pixels >= 1'),
      (self.camera_index >= -1, 'camera_index',
       'use -1 (fitted) or a camera index >= 0'),
      (len(self.background) == 3 and all(
        _finite(c) and 0 <= c <= 1 for c in self.background),
       'background', 'use three numbers in [0, 1] or a name '
       f'({", ".join(BACKGROUNDS)})'),
      (_finite(self.orbit_degrees), 'orbit_degrees',
       'use a finite angle [degrees]'),
      (_finite(self.min_opacity) and 0 <= self.min_opacity < 1,
       'min_opacity', 'use an activated opacity in [0, 1)'),
      (self.ground_height is None or _finite(self.ground_height),
       'ground_height', 'use a finite height [scene units] or None'),
      (_finite(self.floater_factor) and (
        self.floater_factor == 0 or self.floater_factor >= 2),
       'floater_factor', 'use 0 (off) or >= 2 (times the median '
       '8th-neighbour distance)'),
    ])
    for item in self.initial_velocity:
      if not (isinstance(item, (tuple, list)) and len(item) == 2
              and isinstance(item[0], str)
              and isinstance(item[1], (tuple, list, np.ndarray))):
        raise PipelineError(
          f'initial_velocity entry {item!r}: give (object name, (vx, vy, '
          "vz)) pairs, e.g. initial_velocity=(('jelly cube', (1.0, 0.0, "
          "0.0)),), name '' for every object")
      name, v = item
      if len(v) != 3 or not all(_finite(c) for c in v):
        raise PipelineError(
          f'initial_velocity of {name or "every object"!r} is {v!r}: give '
          'three finite numbers [m/s].')
    names = [n for n, _ in self.initial_velocity]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
      raise PipelineError(
        f'initial_velocity names {", ".join(repr(n) for n in twice)} more '
        'than once (one would silently win); give each object one velocity.')

  @property
  def frame_dt(self) -> float:
    return 1.0 / self.fps


@dataclasses.dataclass(frozen=True)
class SimulateConfig:
  """Static settings of :func:`simulate` (hashable: its jit key).

  Attributes:
    num_frames: frames to simulate (the output has ``num_frames + 1``).
    gravity: gravitational acceleration [m/s^2] along -up (0 disables).
    ground: :class:`Ground` contact with the support plane.
    friction: Coulomb friction coefficient of the support plane.
    forces: :class:`ForceSpec` tuple (their vectors are ``Params.forces``).
    use_driver_F: deform Gaussians with the drivers' interpolated F instead
      of the local affine fit of their positions.
    use_mpdp: per-point material fields from MPDP (else uniform means).
    render: :class:`RenderMode`.
    render_config: static rasterizer settings.
    remat_frames: ``jax.checkpoint`` each frame (memory ~ frames). False
      stores every substep's residuals: the tabletop's two-frame
      gradient took 9.1 GB of temporaries and 1.5x the time on the CPU
      (docs/mpm.md); keep True unless the rollout is a few substeps.
    constitutive_kernel: the MPM stress update: 'auto' (one Pallas kernel
      on a CUDA GPU, pure JAX elsewhere), 'jax' or 'pallas'
      (``mpm.SimConfig.constitutive_kernel``).
    gpu_graphs: how a CUDA GPU launches each frame of :func:`run`'s
      simulation: 'substep' (XLA's default, one CUDA graph per substep),
      'frame' (one graph per frame) or 'off' (``mpm.SimConfig.gpu_graphs``;
      the differentiable :func:`simulate` compiles under its caller's
      ``jit`` with XLA's defaults).
  """

  num_frames: int = 60
  gravity: float = 9.8
  ground: Ground = Ground.SLIP
  friction: float = 0.4
  forces: tuple[ForceSpec, ...] = ()
  use_driver_F: bool = False
  use_mpdp: bool = True
  render: RenderMode = RenderMode.FAST
  render_config: raster.RenderConfig = raster.RenderConfig()
  remat_frames: bool = True
  constitutive_kernel: str = 'auto'
  gpu_graphs: str = 'substep'

  def __post_init__(self):
    _check_types('SimulateConfig', self)
    object.__setattr__(self, 'ground',
                       _enum(Ground, self.ground, 'SimulateConfig', 'ground'))
    object.__setattr__(self, 'render', _enum(
      RenderMode, self.render, 'SimulateConfig', 'render'))
    _check('SimulateConfig', self, [
      (self.num_frames >= 1, 'num_frames', 'use >= 1'),
      (_finite(self.gravity), 'gravity', 'use a finite number [m/s^2]'),
      (_finite(self.friction) and self.friction >= 0, 'friction',
       'use a finite friction coefficient >= 0'),
      (self.constitutive_kernel in mpm.CONSTITUTIVE_KERNELS,
       'constitutive_kernel',
       f"use {', '.join(repr(k) for k in mpm.CONSTITUTIVE_KERNELS)}"),
      (self.gpu_graphs in mpm.GPU_GRAPHS, 'gpu_graphs',
       f"use {', '.join(repr(k) for k in mpm.GPU_GRAPHS)}"),
    ])
    if self.gravity < 0:
      _warn_once(f'gravity = {self.gravity} m/s^2 pulls up: the field is '
                 'the magnitude along -up (9.8 for the Earth\'s); keep the '
                 'sign only if objects should fall upwards')


_PREPARE_FIELDS = tuple(f.name for f in dataclasses.fields(PrepareConfig))
_SIMULATE_FIELDS = tuple(f.name for f in dataclasses.fields(SimulateConfig))


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
  """All pipeline settings, flat (scripts and config files write this).

  Every field of :class:`PrepareConfig` and :class:`SimulateConfig` (see
  there), plus ``seed`` (the scripts' PRNG seed for filling and sampling).
  ``.prepare`` and ``.simulate`` give the two parts: ``simulate`` compiles
  once per ``.simulate``, so changing the seed, the grid margin or the
  camera does not recompile it.
  """

  num_frames: int = 60
  fps: float = 30.0
  substeps_per_frame: int | None = None
  cfl: float = 0.4
  max_substeps_per_frame: int = 20_000
  grid_res: int = 48
  margin: float = 0.3
  gravity: float = 9.8
  ground: Ground = Ground.SLIP
  friction: float = 0.4
  sampling: Sampling = Sampling.PGAS_CVT
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
  camera_path: CameraPath = CameraPath.FIXED
  orbit_degrees: float = 360.0
  roi: tuple[float, float, float, float, float, float] | None = None
  min_opacity: float = 0.0
  floater_factor: float = 8.0
  ground_height: float | None = None
  render: RenderMode = RenderMode.FAST
  render_config: raster.RenderConfig = raster.RenderConfig()
  remat_frames: bool = True
  constitutive_kernel: str = 'auto'
  gpu_graphs: str = 'substep'
  seed: int = 0

  def __post_init__(self):
    # Validates (and normalises enums) through the two parts, naming the
    # field as the user wrote it. Forces may be dicts, as in config files.
    if isinstance(self.forces, (tuple, list)):
      object.__setattr__(self, 'forces', tuple(
        _force_from_dict(i, f) if isinstance(f, dict) else f
        for i, f in enumerate(self.forces)))
    _check_types('PipelineConfig', self)
    try:
      p, s = self.prepare, self.simulate
    except PipelineError as e:
      msg = str(e)
      for part in ('PrepareConfig.', 'SimulateConfig.'):
        msg = msg.replace(part, 'PipelineConfig.')
      raise PipelineError(msg) from None
    object.__setattr__(self, 'ground', p.ground)
    object.__setattr__(self, 'sampling', p.sampling)
    object.__setattr__(self, 'camera_path', p.camera_path)
    object.__setattr__(self, 'background', p.background)
    object.__setattr__(self, 'render', s.render)
    duration = self.num_frames / self.fps
    for f in self.forces:
      if f.start >= duration:
        _warn_once(
          f'the {f.kind.value} force on {f.object or "every object"!r} '
          f'starts at {f.start:.3g} s, after the run ends ({self.num_frames} '
          f'frames at {self.fps:g} fps = {duration:.3g} s): it does nothing; '
          'start it earlier or simulate more frames.')

  @property
  def prepare(self) -> PrepareConfig:
    return PrepareConfig(**{k: getattr(self, k) for k in _PREPARE_FIELDS})

  @property
  def simulate(self) -> SimulateConfig:
    return SimulateConfig(**{k: getattr(self, k) for k in _SIMULATE_FIELDS})

  @property
  def frame_dt(self) -> float:
    return 1.0 / self.fps


def _part(config, cls, attr: str):
  """``config`` if it is a ``cls``, its ``attr`` part if a PipelineConfig."""
  if isinstance(config, cls):
    return config
  if isinstance(config, PipelineConfig):
    return getattr(config, attr)
  raise PipelineError(
    f'config is a {type(config).__name__}; give a {cls.__name__} or a '
    'PipelineConfig.')


def as_simulate_config(config: SimulateConfig | PipelineConfig
                       ) -> SimulateConfig:
  """The static simulate config of either config kind."""
  return _part(config, SimulateConfig, 'simulate')


def as_prepare_config(config: PrepareConfig | PipelineConfig
                      ) -> PrepareConfig:
  """The host-side preparation config of either config kind."""
  return _part(config, PrepareConfig, 'prepare')


def _force_from_dict(i: int, f: Any) -> ForceSpec:
  if isinstance(f, ForceSpec):
    return f
  f = dict(f)
  bad = sorted(set(f) - {x.name for x in dataclasses.fields(ForceSpec)})
  if bad:
    raise PipelineError(f'forces[{i}] has unknown fields {bad}; valid: '
                        f'{[x.name for x in dataclasses.fields(ForceSpec)]}')
  for k in ('vector', 'point'):
    if f.get(k) is not None:
      f[k] = _numbers(f'forces[{i}].{k}', f[k], 3)
  return ForceSpec(**f)


def _numbers(field: str, value, n: int) -> tuple[float, ...]:
  """``value`` as ``n`` floats, or a :class:`PipelineError` naming
  ``field`` (a string or a wrong length from a config file or an
  ``--config.*`` override was a ValueError from ``float``)."""
  try:
    out = tuple(float(v) for v in value)
  except (TypeError, ValueError):
    out = ()
  if len(out) != n or isinstance(value, str):
    raise PipelineError(f'PipelineConfig.{field} = {value!r}: give {n} '
                        'numbers, as a tuple')
  return out


def config_from_dict(d) -> PipelineConfig:
  """A :class:`PipelineConfig` from a dict / ConfigDict (lists -> tuples).

  ``forces`` is a list of dicts with :class:`ForceSpec` fields;
  ``initial_velocity`` a list of ``(name, (vx, vy, vz))`` pairs or a dict
  name -> velocity. Unknown keys raise :class:`PipelineError`.
  """
  d = dict(d.to_dict() if hasattr(d, 'to_dict') else d)
  fields = {f.name for f in dataclasses.fields(PipelineConfig)}
  unknown = sorted(set(d) - fields)
  if unknown:
    raise PipelineError(f'unknown pipeline config fields {unknown}; valid: '
                        f'{sorted(fields)}')
  if 'forces' in d:  # (dicts: PipelineConfig converts them)
    d['forces'] = tuple(d['forces'] or ())
  if 'initial_velocity' in d:
    iv = d['initial_velocity'] or ()
    items = iv.items() if isinstance(iv, dict) else iv
    d['initial_velocity'] = tuple(
      (str(n), _numbers(f'initial_velocity[{n!r}]', v, 3))
      for n, v in items)
  if 'background' in d:
    value = d['background']
    if (isinstance(value, (tuple, list)) and len(value) == 1
        and isinstance(value[0], str)):  # --config.background=white
      value = value[0]
    d['background'] = (value if isinstance(value, str)  # a name: checked
                       else _numbers('background', value, 3))
  if d.get('roi') is not None:
    d['roi'] = _numbers('roi', d['roi'], 6)
  if isinstance(d.get('render_config'), dict):
    d['render_config'] = raster.RenderConfig(**d['render_config'])
  return PipelineConfig(**d)
