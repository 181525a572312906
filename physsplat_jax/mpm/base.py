"""Static configuration, materials, forces and state of the MLS-MPM solver.

Three kinds of input never mix (STYLE.md 1):

- ``SimConfig`` / ``GridSpec`` and the boundary-condition dataclasses are
  static, frozen and hashable: changing them recompiles.
- ``Materials`` and ``Forces`` hold differentiable per-particle material
  parameters and force/velocity parameters of the boundary conditions.
- ``MPMState`` is the scan carry: positions, velocities, deformation and
  affine matrices, plastic state and per-particle constants.

Units are SI throughout (m, s, kg, Pa); PhysGaussian configs use the same
units inside their normalised domain (``physsplat_jax.physgaussian``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from physsplat_jax import platforms
from physsplat_jax import struct
from physsplat_jax.mpm.errors import MPMInputError as MPMInputError
from physsplat_jax.mpm.errors import SimulationError as SimulationError
from physsplat_jax.mpm.models import _GENERIC as _GENERIC
from physsplat_jax.mpm.models import CANONICAL_MODELS
from physsplat_jax.mpm.models import MAXWELL_FIELDS
from physsplat_jax.mpm.models import MODEL_DEFAULTS as MODEL_DEFAULTS
from physsplat_jax.mpm.models import model_default as model_default
from physsplat_jax.types import Array
from physsplat_jax.types import device_array
from physsplat_jax.types import is_host_data

INF = float('inf')

# Models whose particles carry an elastic stress that bounds the time step.
ELASTIC_MODELS = (
  'fixed_corotated', 'neo_hookean', 'stvk', 'von_mises', 'drucker_prager',
  'snow', 'foam', 'plasticine', 'newtonian', 'bingham',
)
FLUID_MODELS = ('newtonian',)


# --------------------------------------------------------------------- grid


@dataclasses.dataclass(frozen=True)
class GridSpec:
  """A cubic background grid (static).

  Nodes sit at ``lower + i * dx`` for ``i in [0, res)`` on every axis, with
  ``dx = size / res`` (PhysGaussian's convention: ``n_grid`` cells over
  ``[0, grid_lim]^3``).

  Attributes:
    res: cells (nodes) per axis.
    lower: (3,) domain corner [m].
    size: domain side [m].
  """

  res: int = 32
  lower: tuple[float, float, float] = (0.0, 0.0, 0.0)
  size: float = 1.0

  def __post_init__(self):
    if not isinstance(self.res, int) or self.res < 8:
      raise MPMInputError(
        f'GridSpec.res = {self.res!r}: need an int >= 8 (the quadratic '
        'B-spline stencil and the 3-cell domain border need room).'
      )
    if not self.size > 0:
      raise MPMInputError(f'GridSpec.size = {self.size!r} must be > 0 [m].')
    object.__setattr__(self, 'lower', tuple(float(v) for v in self.lower))
    if len(self.lower) != 3:
      raise MPMInputError(f'GridSpec.lower = {self.lower!r}: need 3 numbers.')

  @property
  def dx(self) -> float:
    """Cell size [m]."""
    return self.size / self.res

  @property
  def inv_dx(self) -> float:
    """1 / dx [1/m]."""
    return self.res / self.size

  @property
  def upper(self) -> tuple[float, float, float]:
    """(3,) far domain corner ``lower + size`` [m]."""
    return tuple(v + self.size for v in self.lower)

  @property
  def num_nodes(self) -> int:
    return self.res ** 3

  @property
  def particle_bounds(self) -> tuple[float, float]:
    """Range of particle coordinates relative to ``lower`` [m].

    Particles are clamped into ``[dx, (res - 2) dx)`` so that their 3x3x3
    stencil always lies inside the grid.
    """
    return self.dx, (self.res - 2.0 - 1e-3) * self.dx


# ------------------------------------------------------ boundary conditions


def _vec3(v, name):
  v = tuple(float(a) for a in v)
  if len(v) != 3 or not all(math.isfinite(a) for a in v):
    raise MPMInputError(f'{name} = {v!r}: need 3 finite numbers.')
  return v


def _unit(v, name):
  v = _vec3(v, name)
  n = math.sqrt(sum(a * a for a in v))
  if not n > 0:
    raise MPMInputError(f'{name} = {v!r} must be a non-zero vector.')
  return tuple(a / n for a in v)


@dataclasses.dataclass(frozen=True)
class SurfaceCollider:
  """A half-space wall ``(x - point) . normal < 0`` acting on grid nodes.

  Attributes:
    point: (3,) a point on the plane [m].
    normal: (3,) plane normal pointing into the free side (normalised).
    surface: 'sticky' (velocity zeroed), 'slip' (normal component removed,
      tangential kept, friction applied) or 'separate' (only the inward
      normal component removed: bodies may lift off; Coulomb friction on the
      tangential part). PhysGaussian's 'cut' is read as 'sticky'.
    friction: Coulomb coefficient for 'slip'/'separate'.
    start_time, end_time: active window [s].
  """

  point: tuple[float, float, float]
  normal: tuple[float, float, float] = (0.0, 0.0, 1.0)
  surface: str = 'sticky'
  friction: float = 0.0
  start_time: float = 0.0
  end_time: float = INF

  def __post_init__(self):
    object.__setattr__(self, 'point', _vec3(self.point, 'point'))
    object.__setattr__(self, 'normal', _unit(self.normal, 'normal'))
    if self.surface not in ('sticky', 'slip', 'separate'):
      raise MPMInputError(
        f'SurfaceCollider.surface = {self.surface!r}; use sticky, slip or '
        'separate.'
      )


@dataclasses.dataclass(frozen=True)
class Cuboid:
  """Grid nodes inside a (moving) box get a prescribed velocity.

  PhysGaussian's ``cuboid``: nodes with ``|x - point(t)|_i < size_i`` take
  ``velocity`` during the window; the box moves with that velocity. With
  ``reset``, all grid velocities are zeroed outside the window until 15
  substeps after ``end_time`` (as PhysGaussian does). ``velocity`` here is
  the default of the differentiable ``Forces`` entry. A fixed box clamps at
  its last held node plane, not its face (docs/mpm.md).

  Attributes:
    point: (3,) box centre at ``start_time`` [m].
    size: (3,) half-extents [m].
    velocity: (3,) [m/s]; zero makes a fixed obstacle.
    start_time, end_time: window [s].
    reset: zero the whole grid outside the window (see above).
  """

  point: tuple[float, float, float]
  size: tuple[float, float, float]
  velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
  start_time: float = 0.0
  end_time: float = INF
  reset: bool = False

  def __post_init__(self):
    for f in ('point', 'size', 'velocity'):
      object.__setattr__(self, f, _vec3(getattr(self, f), f))


@dataclasses.dataclass(frozen=True)
class ParticleImpulse:
  """Adds ``dt * force / m_p`` to selected particles for ``num_dt`` substeps.

  PhysGaussian's ``particle_impulse``: ``force`` [N] acts on *each* selected
  particle, starting at ``start_time``. Particles are selected once, at
  ``init_state``, by ``|x0 - point|_i < size_i`` (all particles when
  ``point`` is None).

  Attributes:
    force: (3,) default force per particle [N] (differentiable via Forces).
    num_dt: number of substeps.
    start_time: [s].
    point, size: (3,) selection box [m] or None.
  """

  force: tuple[float, float, float]
  num_dt: int = 1
  start_time: float = 0.0
  point: tuple[float, float, float] | None = None
  size: tuple[float, float, float] | None = None

  def __post_init__(self):
    object.__setattr__(self, 'force', _vec3(self.force, 'force'))
    if self.point is not None:
      object.__setattr__(self, 'point', _vec3(self.point, 'point'))
      object.__setattr__(self, 'size', _vec3(self.size or (1, 1, 1), 'size'))


@dataclasses.dataclass(frozen=True)
class PointForce:
  """A force on the particles within ``radius`` of a point over a window.

  PhysDreamer's interaction force. Selected once at ``init_state`` by
  ``|x0 - point| < radius``. With ``per_particle`` (PhysDreamer), each
  selected particle receives ``force`` [N]; otherwise ``force`` is the total
  force, shared in proportion to mass (every selected particle accelerates by
  ``force / M_selected``).

  Attributes:
    point: (3,) [m].
    radius: [m].
    force: (3,) default force [N] (differentiable via Forces).
    start_time, end_time: window [s].
    per_particle: see above.
  """

  point: tuple[float, float, float]
  radius: float
  force: tuple[float, float, float]
  start_time: float = 0.0
  end_time: float = INF
  per_particle: bool = True

  def __post_init__(self):
    object.__setattr__(self, 'point', _vec3(self.point, 'point'))
    object.__setattr__(self, 'force', _vec3(self.force, 'force'))
    if not self.radius > 0:
      raise MPMInputError(f'PointForce.radius = {self.radius!r} must be > 0.')


@dataclasses.dataclass(frozen=True)
class EnforceTranslation:
  """Particles initially inside a box move with a prescribed velocity.

  PhysGaussian's ``enforce_particle_translation`` (selection at
  ``init_state``; velocity overwritten before P2G in the window).

  Attributes:
    point, size: (3,) box centre and half-extents [m].
    velocity: (3,) default velocity [m/s] (differentiable via Forces).
    start_time, end_time: window [s].
  """

  point: tuple[float, float, float]
  size: tuple[float, float, float]
  velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
  start_time: float = 0.0
  end_time: float = INF

  def __post_init__(self):
    for f in ('point', 'size', 'velocity'):
      object.__setattr__(self, f, _vec3(getattr(self, f), f))


@dataclasses.dataclass(frozen=True)
class EnforceRotation:
  """Particles initially in a cylinder spin about its axis.

  PhysGaussian's ``enforce_particle_velocity_rotation``: selected particles
  get ``v = rotation_scale * (r_h x normal) + translation_scale * normal``
  (``r_h`` the offset from the axis), i.e. an angular velocity of
  ``-rotation_scale`` [rad/s] about ``normal``, exactly PhysGaussian's
  direction convention.

  Attributes:
    point: (3,) cylinder centre [m].
    normal: (3,) axis (normalised).
    half_height, radius: [m].
    rotation_scale: [rad/s]; translation_scale: [m/s] (both differentiable
      via Forces, as a (2,) entry).
    start_time, end_time: window [s].
  """

  point: tuple[float, float, float]
  normal: tuple[float, float, float]
  half_height: float
  radius: float
  rotation_scale: float = 1.0
  translation_scale: float = 0.0
  start_time: float = 0.0
  end_time: float = INF

  def __post_init__(self):
    object.__setattr__(self, 'point', _vec3(self.point, 'point'))
    object.__setattr__(self, 'normal', _unit(self.normal, 'normal'))


@dataclasses.dataclass(frozen=True)
class SequentialRelease:
  """Holds particles still and releases them layer by layer.

  PhysGaussian's ``release_particles_sequentially``: along axis ``axis``,
  ``num_layers`` nested boxes around ``end_position`` with half-lengths
  ``h (num_layers - i)``, ``h = |start_position - end_position| /
  num_layers``, hold their particles (velocity 0) from ``start_time`` until
  ``end_time (i + 1) / num_layers``. A particle at distance ``d`` from
  ``end_position`` is therefore released at
  ``end_time * ceil(num_layers - d / h) / num_layers`` (farthest first).

  Attributes:
    axis: 0, 1 or 2.
    start_position, end_position: coordinates along the axis [m].
    num_layers: layer count (PhysGaussian forces 50).
    start_time, end_time: [s].
  """

  axis: int
  start_position: float
  end_position: float
  num_layers: int = 50
  start_time: float = 0.0
  end_time: float = 1.0


BOUNDARY_CLASSES = (SurfaceCollider, Cuboid, ParticleImpulse, PointForce,
                    EnforceTranslation, EnforceRotation, SequentialRelease)
# Boundary conditions that select particles at init_state (one (N,) array of
# per-particle data each, in MPMState.bc_data).
PARTICLE_BCS = (ParticleImpulse, PointForce, EnforceTranslation,
                EnforceRotation, SequentialRelease)


def default_force(bc) -> np.ndarray:
  """The default differentiable parameter of a boundary condition."""
  if isinstance(bc, (ParticleImpulse, PointForce)):
    return np.asarray(bc.force)
  if isinstance(bc, (EnforceTranslation, Cuboid)):
    return np.asarray(bc.velocity)
  if isinstance(bc, EnforceRotation):
    return np.asarray([bc.rotation_scale, bc.translation_scale])
  return np.zeros((0,))


# -------------------------------------------------------------------- config


CONSTITUTIVE_KERNELS = ('auto', 'jax', 'pallas')
GPU_GRAPHS = ('substep', 'frame', 'off')


@dataclasses.dataclass(frozen=True)
class SimConfig:
  """Static configuration of an MLS-MPM simulation (frozen, hashable).

  Attributes:
    grid: ``GridSpec``.
    dt: substep [s].
    substeps_per_frame: substeps per output frame.
    num_frames: default frame count for ``rollout``/``run`` (optional).
    gravity: (3,) [m/s^2].
    models: canonical model names present (``CANONICAL_MODELS``); particle
      ``model_id`` indexes this tuple. Models absent cost nothing.
    boundary_conditions: tuple of the dataclasses above. The domain box
      (velocities pointing out of the 3-cell border zeroed, positions
      clamped) is always on.
    rpic_damping: RPIC damping in [0, 1] of the affine matrix C in P2G
      (0 = APIC/MLS).
    grid_v_damping_scale: grid velocities are multiplied by this every
      substep when < 1 (PhysGaussian; >= 1 disables).
    velocity_damping: exponential damping rate of grid velocities [1/s]
      (factor ``exp(-velocity_damping dt)`` per substep).
    num_bodies: number of rigid bodies (particles with ``body_id`` in
      ``[0, num_bodies)`` are rigid).
    body_fixed: per-body flag (length ``num_bodies``): fixed bodies never
      move (tables, pots).
    remat_frames: ``jax.checkpoint`` each frame (backward memory grows with
      frames, not substeps; False: far more memory, docs/mpm.md).
    sort_particles: sort particles by grid cell at the start of every frame
      (better memory locality in the scatter; transparent to callers).
    dtype: 'float32' or 'float64'.
    model_counts: particles per model (aligned with ``models``; rigid
      particles exactly the 'rigid' model's): each model's return mapping
      and the rigid projection then run on their own particles only (the
      pipeline sets it). None: every model evaluated on every particle.
    constitutive_kernel: 'auto' (the stress update as one Pallas kernel on
      a CUDA GPU, ``mpm.pallas_constitutive``, else pure JAX), 'jax' (pure
      JAX everywhere) or 'pallas' (the kernel everywhere; interpreted off a
      GPU: tests); same values and gradients.
    gpu_graphs: how :func:`run` has a GPU launch a frame: 'substep' (a CUDA
      graph per substep, XLA's default), 'frame' (one graph) or 'off'.
    solid_viscosity: the solids' ``Materials.viscosity`` [Pa s] adds a
      Kelvin-Voigt stress ``J eta (C + C^T - 2/3 tr(C) I)`` (damping of
      deformation only; ``models.KELVIN_VOIGT_MODELS``). Off: not computed.
    maxwell: the solids carry a Maxwell branch (``MPMState.F_N``, the
      ``Materials.maxwell_*`` fields): a viscoelastic stress that relaxes
      (Physics3D's, after Fang et al. 2019). Off: not computed.
  """

  grid: GridSpec = GridSpec()
  dt: float = 1e-4
  substeps_per_frame: int = 1
  num_frames: int | None = None
  gravity: tuple[float, float, float] = (0.0, 0.0, -9.8)
  models: tuple[str, ...] = ('fixed_corotated',)
  boundary_conditions: tuple[Any, ...] = ()
  rpic_damping: float = 0.0
  grid_v_damping_scale: float = 1.1
  velocity_damping: float = 0.0
  num_bodies: int = 0
  body_fixed: tuple[bool, ...] = ()
  remat_frames: bool = True
  sort_particles: bool = True
  dtype: str = 'float32'
  model_counts: tuple[int, ...] | None = None
  constitutive_kernel: str = 'auto'
  gpu_graphs: str = 'substep'
  solid_viscosity: bool = False
  maxwell: bool = False

  def __post_init__(self):
    if not isinstance(self.grid, GridSpec):
      raise MPMInputError(f'SimConfig.grid must be a GridSpec, got '
                          f'{type(self.grid).__name__}.')
    if not self.dt > 0:
      raise MPMInputError(f'SimConfig.dt = {self.dt!r} must be > 0 [s].')
    if int(self.substeps_per_frame) < 1:
      raise MPMInputError(f'SimConfig.substeps_per_frame = '
                          f'{self.substeps_per_frame!r} must be >= 1.')
    object.__setattr__(self, 'substeps_per_frame',
                       int(self.substeps_per_frame))
    object.__setattr__(self, 'gravity', _vec3(self.gravity, 'gravity'))
    models = tuple(self.models)
    if not models:
      raise MPMInputError('SimConfig.models is empty; name at least one model '
                          f'from {list(CANONICAL_MODELS)}.')
    for m in models:
      if m not in CANONICAL_MODELS:
        raise MPMInputError(
          f'SimConfig.models: unknown model {m!r}; use names from '
          f'{list(CANONICAL_MODELS)} (physsplat_jax.mpm.models.'
          'canonical_model maps names such as "jelly").'
        )
    if len(set(models)) != len(models):
      raise MPMInputError(f'SimConfig.models = {models} has duplicates.')
    object.__setattr__(self, 'models', models)
    bcs = tuple(self.boundary_conditions)
    for i, bc in enumerate(bcs):
      if not isinstance(bc, BOUNDARY_CLASSES):
        raise MPMInputError(
          f'SimConfig.boundary_conditions[{i}] is a {type(bc).__name__}; '
          'use the dataclasses of physsplat_jax.mpm (SurfaceCollider, '
          'Cuboid, ParticleImpulse, PointForce, EnforceTranslation, '
          'EnforceRotation, SequentialRelease).')
    object.__setattr__(self, 'boundary_conditions', bcs)
    if not 0.0 <= self.rpic_damping <= 1.0:
      raise MPMInputError(f'SimConfig.rpic_damping = {self.rpic_damping} must '
                          'be in [0, 1].')
    fixed = tuple(bool(b) for b in self.body_fixed)
    if self.num_bodies < 0:
      raise MPMInputError('SimConfig.num_bodies must be >= 0.')
    fixed = fixed or (False,) * self.num_bodies
    if len(fixed) != self.num_bodies:
      raise MPMInputError(
        f'SimConfig.body_fixed has {len(fixed)} entries for num_bodies = '
        f'{self.num_bodies}; give one flag per body.')
    object.__setattr__(self, 'body_fixed', fixed)
    object.__setattr__(self, 'solid_viscosity', bool(self.solid_viscosity))
    object.__setattr__(self, 'maxwell', bool(self.maxwell))
    if self.model_counts is not None:
      mc = tuple(int(c) for c in self.model_counts)
      if len(mc) != len(models) or min(mc) < 0 or (
          self.num_bodies and 'rigid' not in models):
        raise MPMInputError(
          f'SimConfig.model_counts = {mc}: give one count >= 0 per model of '
          f'{models} (with rigid bodies, one of them "rigid"), or None.')
      object.__setattr__(self, 'model_counts', mc)
    for field, choices in (('constitutive_kernel', CONSTITUTIVE_KERNELS),
                           ('gpu_graphs', GPU_GRAPHS),
                           ('dtype', ('float32', 'float64'))):
      if getattr(self, field) not in choices:
        raise MPMInputError(
          f'SimConfig.{field} = {getattr(self, field)!r}; use '
          f"{', '.join(repr(k) for k in choices)}.")
    if (self.constitutive_kernel == 'pallas'
        and platforms.pallas_triton() is None):
      raise MPMInputError(
        "SimConfig.constitutive_kernel = 'pallas': " +
        platforms.triton_missing("constitutive_kernel='auto' or 'jax'"))

  @property
  def frame_dt(self) -> float:
    """Time between frames [s]."""
    return self.dt * self.substeps_per_frame

  @property
  def jnp_dtype(self):
    return jnp.float64 if self.dtype == 'float64' else jnp.float32

  @property
  def model_index(self) -> dict[str, int]:
    return {m: i for i, m in enumerate(self.models)}

  @property
  def particle_bcs(self) -> tuple[int, ...]:
    """Indices of boundary conditions that carry per-particle data."""
    return tuple(i for i, bc in enumerate(self.boundary_conditions)
                 if isinstance(bc, PARTICLE_BCS))

  def replace(self, **kwargs) -> 'SimConfig':
    return dataclasses.replace(self, **kwargs)


# ----------------------------------------------------------------- materials


class Materials(struct.PyTreeNode):
  """Per-particle material parameters (differentiable leaves, all (N,)).

  Attributes:
    E: Young's modulus [Pa]. For fluids only the bulk modulus
      ``K = E / (3 (1 - 2 nu))`` is used.
    nu: Poisson ratio in [0, 0.5).
    rho: density [kg/m^3].
    yield_stress: yield stress [Pa] (von_mises, plasticine, foam, bingham;
      each one's convention in mpm.constitutive).
    hardening: isotropic hardening switch/multiplier (PhysGaussian's
      ``hardening``, 0 or 1): yield grows by ``hardening * 2 mu xi`` per unit
      plastic strain (von_mises, plasticine).
    xi: hardening rate (von_mises, plasticine) or Stomakhin's snow hardening
      coefficient (snow: stiffness ``* exp(xi (1 - Jp))``).
    softening: yield softening per unit plastic strain [Pa] (plasticine;
      the particle is damaged, stress-free, once its yield reaches 0).
    friction_angle: Drucker-Prager friction angle [deg].
    dp_h1, dp_h2, dp_h3: Klar et al. (2016) hardening
      ``phi(q) = friction_angle + (h1 q - h3) exp(-h2 q)`` [deg, -, deg] with
      ``q`` the accumulated plastic strain; h1 = h3 = 0 disables it.
    plastic_viscosity: foam viscoplastic viscosity [Pa s].
    viscosity: dynamic viscosity [Pa s] (newtonian; plastic for bingham;
      a solid's Kelvin-Voigt damping with ``SimConfig.solid_viscosity``).
    theta_c, theta_s: snow critical compression and stretch.
    dp_cohesion: Drucker-Prager cohesion as the log-strain ``c`` of the cone
      apex (Tampubolon et al. 2017): the sand carries isotropic tension up
      to a volumetric log-strain ``3 c`` (tensile strength about
      ``(3 lam + 2 mu) c``); 0 is cohesionless.
    dp_volume_correction: 1 enables Tampubolon et al. (2017)'s volume
      correction (the log-volume gained at the cone apex is stored in
      ``log Jp`` and given back before the material resists compression
      again, so dilated sand does not push itself apart), 0 is Klar et al.
      (2016) as in PhysGaussian.
    model_id: (N,) int32 index into ``SimConfig.models``.
    maxwell_E, maxwell_nu, maxwell_viscosity: a solid's Maxwell branch
      (``SimConfig.maxwell``; None otherwise): the Young's modulus [Pa] and
      Poisson ratio of its Hencky spring and its dashpot's viscosity [Pa s]
      (``constitutive.maxwell_update``).
  """

  E: Array
  nu: Array
  rho: Array
  yield_stress: Array
  hardening: Array
  xi: Array
  softening: Array
  friction_angle: Array
  dp_h1: Array
  dp_h2: Array
  dp_h3: Array
  plastic_viscosity: Array
  viscosity: Array
  theta_c: Array
  theta_s: Array
  dp_cohesion: Array
  dp_volume_correction: Array
  model_id: Array
  maxwell_E: Array | None = None
  maxwell_nu: Array | None = None
  maxwell_viscosity: Array | None = None

  @property
  def num(self) -> int:
    return self.E.shape[0]

  def lame(self):
    """(mu, lam) Lame parameters [Pa]."""
    return lame(self.E, self.nu)


FLOAT_FIELDS = (
  'E', 'nu', 'rho', 'yield_stress', 'hardening', 'xi', 'softening',
  'friction_angle', 'dp_h1', 'dp_h2', 'dp_h3', 'plastic_viscosity',
  'viscosity', 'theta_c', 'theta_s', 'dp_cohesion', 'dp_volume_correction',
)

def lame(E, nu):
  """Lame parameters ``(mu, lam)`` from Young's modulus and Poisson ratio."""
  mu = E / (2.0 * (1.0 + nu))
  lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
  return mu, lam


def make_materials(
  models: Sequence[str] | Array,
  E, nu, rho,
  config_models: Sequence[str] | None = None,
  num: int | None = None,
  dtype=None,
  **overrides,
) -> Materials:
  """Builds per-particle ``Materials`` with per-model defaults.

  Args:
    models: either a model name for all particles ('snow'), a sequence of
      names per particle, or an (N,) int array of indices into
      ``config_models``.
    E, nu, rho: scalars or (N,) arrays [Pa, -, kg/m^3].
    config_models: the ``SimConfig.models`` tuple that ``model_id`` indexes;
      default: the distinct names of ``models`` in first-seen order (required
      when ``models`` is an int array).
    num: particle count N when every argument is a scalar.
    dtype: float dtype (default: float32, or the dtype of E if an array).
    **overrides: any other ``Materials`` float field (scalar or (N,)),
      replacing the model defaults (a ``maxwell_*`` field gives all three).

  Returns:
    ``Materials`` with (N,) leaves.

  Raises:
    ValueError: unknown model or field name, inconsistent lengths.
  """
  for k in overrides:
    if k not in FLOAT_FIELDS + MAXWELL_FIELDS:
      raise MPMInputError(f'make_materials: unknown field {k!r}; fields are '
                          f'{list(FLOAT_FIELDS + MAXWELL_FIELDS)}.')
  if isinstance(models, str):
    names = None
    single = models
  elif isinstance(models, (list, tuple)) and models and isinstance(
      models[0], str):
    names = list(models)
    single = None
  else:
    names = None
    single = None
  sizes = [np.shape(a)[0] for a in (E, nu, rho, *overrides.values())
           if np.ndim(a) == 1]
  if names is not None:
    sizes.append(len(names))
  if single is None and names is None:
    sizes.append(np.shape(models)[0])
  if num is not None:
    sizes.append(num)
  if not sizes:
    raise MPMInputError('make_materials: cannot tell the particle count; pass '
                        'num=N or an (N,) array.')
  if len(set(sizes)) != 1:
    raise MPMInputError(
      f'make_materials: inconsistent particle counts {sizes}.')
  n = sizes[0]
  if dtype is None:
    dtype = (E.dtype if isinstance(E, jax.Array) and jnp.issubdtype(
      E.dtype, jnp.floating) else jnp.float32)
  if single is not None:
    names = [single] * n
  if names is not None:
    for m in set(names):
      if m not in CANONICAL_MODELS:
        raise MPMInputError(f'make_materials: unknown model {m!r}; use one of '
                            f'{list(CANONICAL_MODELS)}.')
    if config_models is None:
      config_models = tuple(dict.fromkeys(names))
    idx = {m: i for i, m in enumerate(config_models)}
    for m in set(names):
      if m not in idx:
        raise MPMInputError(f'make_materials: model {m!r} is not in '
                            f'config_models {tuple(config_models)}.')
    model_id = np.asarray([idx[m] for m in names], np.int32)
    per_particle = names
  else:
    if config_models is None:
      raise MPMInputError(
        'make_materials: pass config_models when models is an '
        'array of indices.')
    model_id = np.asarray(models, np.int32)
    if model_id.size and (model_id.min() < 0
                          or model_id.max() >= len(config_models)):
      raise MPMInputError(f'make_materials: model ids out of range '
                          f'[0, {len(config_models)}).')
    per_particle = [config_models[i] for i in model_id]
  fields = {}
  # (The Maxwell branch's fields only when one of them is given.)
  maxwell = MAXWELL_FIELDS if set(MAXWELL_FIELDS) & set(overrides) else ()
  for f in FLOAT_FIELDS[3:] + maxwell:
    if f in overrides:
      fields[f] = _per_particle(overrides[f], n, dtype)
    else:
      table = np.asarray([model_default(m, f) for m in config_models])
      fields[f] = device_array(table[model_id], dtype)
  del per_particle
  return Materials(E=_per_particle(E, n, dtype),
                   nu=_per_particle(nu, n, dtype),
                   rho=_per_particle(rho, n, dtype),
                   model_id=device_array(model_id), **fields)


def _per_particle(a, n: int, dtype) -> Array:
  """``a`` (scalar or (n,)) as (n,): host data broadcast in NumPy (in jnp
  each new count compiled a program per field), JAX arrays in jnp."""
  if not is_host_data(a):
    return jnp.broadcast_to(jnp.asarray(a, dtype), (n,))
  return device_array(np.broadcast_to(np.asarray(a, jnp.dtype(dtype)), (n,)))


# -------------------------------------------------------------------- forces


class Forces(struct.PyTreeNode):
  """Differentiable parameters of the boundary conditions.

  Attributes:
    values: tuple aligned with ``SimConfig.boundary_conditions``: (3,) force
      [N] for ``ParticleImpulse``/``PointForce``, (3,) velocity [m/s] for
      ``EnforceTranslation``/``Cuboid``, (2,) (rotation_scale [rad/s],
      translation_scale [m/s]) for ``EnforceRotation``, (0,) otherwise.
  """

  values: tuple[Array, ...] = ()


def make_forces(config: SimConfig, dtype=None) -> Forces:
  """The default ``Forces`` of ``config`` (values from the dataclasses)."""
  dtype = dtype or config.jnp_dtype
  return Forces(values=tuple(
    jnp.asarray(default_force(bc), dtype) for bc in config.boundary_conditions
  ))


# --------------------------------------------------------------------- state


class MPMState(struct.PyTreeNode):
  """Particle state (the carry of the frame scan).

  The public layout is particle-first; internally each frame converts to
  structure of arrays (particle index last) for speed.

  Attributes:
    x: (N, 3) positions [m].
    v: (N, 3) velocities [m/s].
    F: (N, 3, 3) deformation gradient (elastic part after the latest return
      mapping, times the latest G2P increment: PhysGaussian's ``F_trial``).
    C: (N, 3, 3) APIC/MLS affine velocity matrix [1/s].
    Jp: (N,) snow plastic volume ratio (1 at rest; other models keep 1).
    ep: (N,) accumulated plastic strain (von Mises family) or Drucker-Prager
      hardening state q.
    vol0: (N,) initial volumes [m^3].
    mass: (N,) masses ``rho * vol0`` [kg].
    body_id: (N,) int32 rigid body of each particle (-1: not rigid).
    bc_data: tuple of (N,) arrays, one per particle boundary condition
      (``SimConfig.particle_bcs``): a 0/1 selection mask, or the release time
      [s] for ``SequentialRelease``.
    t: () time [s].
    step: () int32 substeps taken.
    F_N: (N, 3, 3) the Maxwell branch's elastic deformation gradient
      (``SimConfig.maxwell``; None otherwise).
  """

  x: Array
  v: Array
  F: Array
  C: Array
  Jp: Array
  ep: Array
  vol0: Array
  mass: Array
  body_id: Array
  bc_data: tuple[Array, ...]
  t: Array
  step: Array
  F_N: Array | None = None

  @property
  def num(self) -> int:
    return self.x.shape[0]

  @property
  def J(self) -> Array:
    """(N,) ``det F``."""
    return jnp.linalg.det(self.F)
