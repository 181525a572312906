"""PhysGaussian ``config/*.json`` scene configs, parsed as static dataclasses.

Accepts the schema of PhysGaussian (Xie et al., CVPR 2024,
``utils/decode_param.py``) as is, with the same defaults:

- material: ``material`` (name or id 0..6), ``E`` [Pa, normalised domain],
  ``nu`` in [0, 0.5], ``density`` [kg/m^3], ``g`` (scalar or 3-vector
  [m/s^2]), ``n_grid`` cells over ``[0, grid_lim]^3``; optional
  ``yield_stress``, ``hardening``, ``xi``, ``friction_angle`` [deg],
  ``plastic_viscosity``, ``softening``, ``rpic_damping``,
  ``grid_v_damping_scale`` and ``additional_material_params`` (boxes
  ``{point, size, E, nu, density}`` that override the material inside
  ``|x - point|_i < size_i`` on every axis).
- time: ``substep_dt``, ``frame_dt``, ``frame_num`` [s, s, frames].
- preprocessing: ``opacity_threshold``, ``rotation_degree[]`` /
  ``rotation_axis[]``, ``sim_area``, ``scale``, ``particle_filling{...}``.
- camera: ``mpm_space_vertical_upward_axis``, ``mpm_space_viewpoint_center``,
  ``default_camera_index``, ``init_azimuthm`` [sic], ``init_elevation``,
  ``init_radius``, ``move_camera``, ``delta_a``, ``delta_e``, ``delta_r``,
  ``show_hint`` (honoured by :mod:`physsplat_jax.physgaussian.camera`).
- ``boundary_conditions``: a list of ``{type, ...}`` with the types of
  PhysGaussian's ``set_boundary_conditions``.

Normalised domain (PhysGaussian ``transform2origin`` + ``shift2center111``):
after the rotations ``R = R_k ... R_1`` (each ``rotation_degree[i]`` degrees
about axis ``rotation_axis[i]``), the selected positions are mapped as

  x_n = (R x - c) * s + (1, 1, 1),   c = (min + max) / 2,
  s = scale / max_i(max_i - min_i),

so the object fits a cube of side ``scale`` centred at (1, 1, 1) inside
``[0, grid_lim]^3``. E, forces, impulses and velocities in the config are in
these normalised units (REFERENCE.md §1.4-1.5); ``denormalise_positions``
inverts the map: ``x = R^T ((x_n - 1) / s + c)``.

Material names map to the package's canonical constitutive models:
jelly (0) -> fixed_corotated, metal (1) -> von_mises, sand (2) ->
drucker_prager, foam (3) -> foam, snow (4) -> snow, plasticine (5) ->
plasticine, neo-hookean (6, PhysDreamer) -> neo_hookean; canonical names
('stvk', 'newtonian', 'bingham', 'rigid', ...) are accepted too.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import os
from typing import Any

import jax.numpy as jnp
import numpy as np
from absl import logging

from physsplat_jax import struct
from physsplat_jax.mpm.models import CANONICAL_MODELS
from physsplat_jax.mpm.models import KELVIN_VOIGT_MODELS
from physsplat_jax.mpm.models import MATERIAL_ALIASES
from physsplat_jax.mpm.models import MATERIAL_IDS
from physsplat_jax.mpm.models import canonical_model
from physsplat_jax.physgaussian.fields import ConfigError
from physsplat_jax.physgaussian.fields import _bool
from physsplat_jax.physgaussian.fields import _check_kind
from physsplat_jax.physgaussian.fields import _float
from physsplat_jax.physgaussian.fields import _freeze
from physsplat_jax.physgaussian.fields import _int
from physsplat_jax.physgaussian.fields import _type_error
from physsplat_jax.physgaussian.fields import _vec
from physsplat_jax.physgaussian.fields import _where
from physsplat_jax.physgaussian.fields import check_keys
from physsplat_jax.physgaussian.fields import check_range
from physsplat_jax.types import Array

# The plasticity fields a config carries, checked against their physical
# ranges (mpm.models.PARAM_RANGES).
_PLASTICITY_FIELDS = ('friction_angle', 'yield_stress', 'plastic_viscosity',
                      'hardening', 'xi', 'softening')

BOUNDARY_TYPES = (
  'bounding_box', 'cuboid', 'particle_impulse', 'enforce_particle_translation',
  'enforce_particle_velocity_rotation', 'surface_collider',
  'release_particles_sequentially',
)

# Required fields (name -> expected kind) per boundary-condition type, as
# read by PhysGaussian's set_boundary_conditions.
_BC_FIELDS = {
  'bounding_box': {},
  'cuboid': {'point': 'vec3', 'size': 'vec3', 'velocity': 'vec3',
             'start_time': 'float', 'end_time': 'float'},
  'particle_impulse': {'force': 'vec3'},
  'enforce_particle_translation': {'point': 'vec3', 'size': 'vec3',
                                   'velocity': 'vec3', 'start_time': 'float',
                                   'end_time': 'float'},
  'enforce_particle_velocity_rotation': {
    'point': 'vec3', 'normal': 'vec3', 'half_height_and_radius': 'vec2',
    'rotation_scale': 'float', 'translation_scale': 'float',
    'start_time': 'float', 'end_time': 'float'},
  'surface_collider': {'point': 'vec3', 'normal': 'vec3',
                       'surface': 'str', 'friction': 'float',
                       'start_time': 'float', 'end_time': 'float'},
  'release_particles_sequentially': {},
}
# Every other key is refused (a typo would silently fall back to a default).
_BC_OPTIONAL = {
  # PhysGaussian's add_bounding_box takes a window but is always on; the
  # keys are accepted (with a warning) and ignored, as there.
  'bounding_box': {'start_time': 'float', 'end_time': 'float'},
  'cuboid': {'reset': 'int'},
  # PhysGaussian's set_boundary_conditions defaults: num_dt 1, start_time
  # 0, point and size (1, 1, 1).
  'particle_impulse': {'num_dt': 'int', 'start_time': 'float',
                       'point': 'vec3', 'size': 'vec3'},
  # PhysGaussian's fields (it requires all of them); 'axis' is our
  # alternative to 'normal'. Checked for type here, for presence when
  # simulated (physsplat_jax.physgaussian).
  'release_particles_sequentially': {
    'normal': 'vec3', 'axis': 'int', 'start_position': 'float',
    'end_position': 'float', 'num_layers': 'int', 'start_time': 'float',
    'end_time': 'float'},
}
SURFACE_TYPES = ('sticky', 'slip', 'cut')

_KNOWN_TOP = {
  'material', 'E', 'nu', 'density', 'g', 'grid_lim', 'n_grid',
  'yield_stress', 'hardening', 'xi', 'friction_angle', 'plastic_viscosity',
  'softening', 'rpic_damping', 'grid_v_damping_scale', 'mu_N', 'lam_N',
  'viscosity',
  'additional_material_params', 'substep_dt', 'frame_dt', 'frame_num',
  'opacity_threshold', 'rotation_degree', 'rotation_axis', 'sim_area',
  'scale', 'particle_filling', 'mpm_space_vertical_upward_axis',
  'mpm_space_viewpoint_center', 'default_camera_index', 'init_azimuthm',
  'init_elevation', 'init_radius', 'move_camera', 'delta_a', 'delta_e',
  'delta_r', 'show_hint', 'boundary_conditions',
}

# Fields that are parsed and validated but that no part of this package acts
# on yet (docs/configs.md); a one-line warning names those present.
# Honoured in part: particle_filling's sub-fields search_threshold,
# search_exclude_direction, ray_cast_direction, smooth and visualize have no
# counterpart in physsplat_jax.sampling.filling (docs/configs.md).
PARTLY_HONOURED = ('particle_filling',)
NOT_HONOURED = ()


# ----------------------------------------------------------------- dataclasses


@dataclasses.dataclass(frozen=True)
class MaterialBox:
  """An ``additional_material_params`` entry (normalised units).

  Attributes:
    point: box centre (3,) [normalised length].
    size: box half-extents (3,) [normalised length].
    E: Young's modulus inside the box [Pa]; None sets the base value
      (also over an earlier box).
    nu: Poisson ratio inside the box; None sets the base value.
    density: density inside the box [kg/m^3]; None sets the base value
      (PhysGaussian's decode_param fills a missing density with the base
      density; it requires E and nu).
  """

  point: tuple[float, float, float]
  size: tuple[float, float, float]
  E: float | None = None
  nu: float | None = None
  density: float | None = None


@dataclasses.dataclass(frozen=True)
class BoundaryCondition:
  """One ``boundary_conditions`` entry.

  Attributes:
    type: one of ``BOUNDARY_TYPES``.
    params: sorted ``(name, value)`` pairs; lists become tuples.
  """

  type: str
  params: tuple[tuple[str, Any], ...] = ()

  def get(self, name: str, default: Any = None) -> Any:
    """Returns the value of field ``name`` or ``default``."""
    return dict(self.params).get(name, default)


@dataclasses.dataclass(frozen=True)
class ParticleFilling:
  """PhysGaussian ``particle_filling`` block (parsed; see docs/configs.md)."""

  params: tuple[tuple[str, Any], ...] = ()

  def get(self, name: str, default: Any = None) -> Any:
    """Returns the value of field ``name`` or ``default``."""
    return dict(self.params).get(name, default)


@dataclasses.dataclass(frozen=True)
class CameraConfig:
  """PhysGaussian camera fields (the video camera of
  :mod:`physsplat_jax.physgaussian.camera`; ``init_azimuth`` is the JSON's
  ``init_azimuthm``)."""

  vertical_upward_axis: tuple[float, ...] = (0.0, 0.0, 1.0)
  viewpoint_center: tuple[float, ...] = (1.0, 1.0, 1.0)
  default_camera_index: int = 0
  init_azimuth: float = 0.0
  init_elevation: float = 0.0
  init_radius: float = 0.0
  move_camera: bool = False
  delta_a: float = 0.0
  delta_e: float = 0.0
  delta_r: float = 0.0
  show_hint: bool = False


@dataclasses.dataclass(frozen=True)
class PhysGaussianConfig:
  """A parsed PhysGaussian scene config: frozen and hashable (static).

  Attributes:
    material: canonical constitutive-model name (``CANONICAL_MODELS``).
    E: Young's modulus [Pa in normalised units].
    nu: Poisson ratio in [0, 0.5].
    density: [kg/m^3].
    g: gravity (3,) [m/s^2, normalised]; a scalar ``g`` means (0, 0, -g).
    n_grid: grid cells per axis.
    grid_lim: domain side; the grid spans ``[0, grid_lim]^3``.
    substep_dt: substep [s].
    frame_dt: frame interval [s].
    frame_num: number of frames.
    rpic_damping: RPIC damping in [0, 1] (0 = plain APIC/MLS).
    grid_v_damping_scale: per-substep grid velocity factor, > 0 (>= 1
      disables).
    yield_stress, hardening, xi, friction_angle, plastic_viscosity,
      softening: plasticity parameters (friction_angle in degrees).
    mu_N, lam_N, viscosity: Physics3D's viscoelastic (Maxwell) branch, its
      Lame parameters [Pa] and its dashpot's viscosity [Pa s]; a branch
      when mu_N > 0, on a solid (``mpm.SimConfig.maxwell``).
    additional_material_params: boxes overriding E/nu/density.
    boundary_conditions: tuple of ``BoundaryCondition``.
    opacity_threshold: Gaussians with sigmoid(opacity) below it are dropped.
    rotation_degree, rotation_axis: preprocessing rotations (deg, 0/1/2).
    sim_area: ``(xmin, xmax, ymin, ymax, zmin, zmax)`` after rotation, or
      None for everything.
    scale: side of the cube the object is scaled into (default 1).
    particle_filling: ``ParticleFilling`` or None.
    camera: ``CameraConfig``.
    source: where the config came from (for messages).
  """

  material: str = 'fixed_corotated'
  E: float = 1e5
  nu: float = 0.4
  density: float = 200.0
  g: tuple[float, float, float] = (0.0, 0.0, -9.8)
  n_grid: int = 50
  grid_lim: float = 2.0
  substep_dt: float = 1e-4
  frame_dt: float = 1e-2
  frame_num: int = 100
  rpic_damping: float = 0.0
  grid_v_damping_scale: float = 1.1
  yield_stress: float = 1e6
  hardening: float = 0.0
  xi: float = 0.0
  friction_angle: float = 25.0
  plastic_viscosity: float = 0.0
  softening: float = 0.1
  mu_N: float = 0.0
  lam_N: float = 0.0
  viscosity: float = 0.0
  additional_material_params: tuple[MaterialBox, ...] = ()
  boundary_conditions: tuple[BoundaryCondition, ...] = ()
  opacity_threshold: float = 0.02
  rotation_degree: tuple[float, ...] = ()
  rotation_axis: tuple[int, ...] = ()
  sim_area: tuple[float, ...] | None = None
  scale: float = 1.0
  particle_filling: ParticleFilling | None = None
  camera: CameraConfig = CameraConfig()
  source: str = '<dict>'

  @property
  def dx(self) -> float:
    """Grid spacing [normalised length]."""
    return self.grid_lim / self.n_grid

  @property
  def maxwell_params(self) -> dict[str, float]:
    """Physics3D's viscoelastic branch as ``mpm.Materials`` fields:
    ``maxwell_E``, ``maxwell_nu`` of the Lame pair ``(mu_N, lam_N)`` and
    ``maxwell_viscosity``; empty without a branch (``mu_N = 0``)."""
    if not self.mu_N > 0:
      return {}
    mu, lam = float(self.mu_N), float(self.lam_N)
    return dict(maxwell_E=mu * (3 * lam + 2 * mu) / (lam + mu),
                maxwell_nu=lam / (2 * (lam + mu)),
                maxwell_viscosity=float(self.viscosity))

  @property
  def substeps_per_frame(self) -> int:
    """``round(frame_dt / substep_dt)``, as PhysGaussian's step count."""
    return max(1, int(round(self.frame_dt / self.substep_dt)))

  def replace(self, **kwargs) -> 'PhysGaussianConfig':
    """Returns a copy with fields replaced (re-validated)."""
    return _validate(dataclasses.replace(self, **kwargs))


class MaterialParams(struct.PyTreeNode):
  """Differentiable scalar material parameters (float arrays, shape ()).

  Attributes:
    E: Young's modulus [Pa].
    nu: Poisson ratio.
    density: [kg/m^3].
    yield_stress: [Pa].
    hardening: von Mises hardening coefficient.
    xi: hardening rate.
    friction_angle: [deg].
    plastic_viscosity: [Pa s].
    softening: plasticine softening.
  """

  E: Array
  nu: Array
  density: Array
  yield_stress: Array
  hardening: Array
  xi: Array
  friction_angle: Array
  plastic_viscosity: Array
  softening: Array


class NormTransform(struct.PyTreeNode):
  """Map from input (PLY) coordinates to the normalised simulation domain.

  ``x_n = (R x - centre) * scale + offset``.

  Attributes:
    rotation: (3, 3) preprocessing rotation R.
    centre: (3,) bounding-box centre of the rotated, selected points.
    scale: () factor ``scale / max extent``.
    offset: (3,) shift, (1, 1, 1) as in PhysGaussian.
  """

  rotation: Array
  centre: Array
  scale: Array
  offset: Array


# --------------------------------------------------------------------- parsing


def material_name(value: Any, source: str = '<dict>') -> str:
  """Maps a PhysGaussian material name or id to a canonical model name.

  Args:
    value: e.g. 'jelly', 'sand', 2, or a canonical name like 'stvk'.
    source: config path, for the error message.

  Returns:
    One of ``CANONICAL_MODELS``.

  Raises:
    ConfigError: unknown name or id.
  """
  if isinstance(value, bool):
    raise _type_error(source, 'material', value, 'a material name or id')
  if isinstance(value, (int, float)) and float(value).is_integer():
    if int(value) in MATERIAL_IDS:
      return MATERIAL_IDS[int(value)]
    raise ConfigError(
      f'{_where(source, "material")}: unknown material id {value!r}; '
      f'PhysGaussian ids are {sorted(MATERIAL_IDS)} '
      '(0 jelly, 1 metal, 2 sand, 3 foam, 4 snow, 5 plasticine, '
      '6 neo-hookean).'
    )
  if not isinstance(value, str):
    raise _type_error(source, 'material', value, 'a material name or id')
  model = canonical_model(value)
  if model is not None:
    return model
  raise ConfigError(
    f'{_where(source, "material")}: unknown material {value!r}; use one of '
    f'{sorted(MATERIAL_ALIASES)} (PhysGaussian names) or '
    f'{list(CANONICAL_MODELS)}.'
  )


def _parse_box(source, i, box):
  field = f'additional_material_params[{i}]'
  if not isinstance(box, dict):
    raise _type_error(source, field, box, 'an object {point, size, ...}')
  for k in box:
    if k not in ('point', 'size', 'E', 'nu', 'density'):
      raise ConfigError(
        f'{_where(source, field)}: unknown key {k!r}; expected point, size, '
        'E, nu, density.'
      )
  for k in ('point', 'size'):
    if k not in box:
      raise ConfigError(f'{_where(source, field)}: missing {k!r} (3 numbers).')
  opt = {
    k: _float(source, f'{field}.{k}', box[k])
    for k in ('E', 'nu', 'density') if k in box
  }
  return MaterialBox(
    point=_vec(source, f'{field}.point', box['point'], 3),
    size=_vec(source, f'{field}.size', box['size'], 3),
    **opt,
  )


def _parse_bc(source, i, bc, warn=True):
  field = f'boundary_conditions[{i}]'
  if not isinstance(bc, dict):
    raise _type_error(source, field, bc, 'an object with a "type"')
  kind = bc.get('type')
  if kind not in BOUNDARY_TYPES:
    raise ConfigError(
      f'{_where(source, field + ".type")}: unknown boundary condition '
      f'{kind!r}; expected one of {list(BOUNDARY_TYPES)}.'
    )
  required = _BC_FIELDS[kind]
  optional = _BC_OPTIONAL.get(kind, {})
  check_keys(source, field, bc, {'type', *required, *optional}, kind)
  params = {}
  for name, want in required.items():
    if name not in bc:
      if name in ('start_time', 'end_time'):
        continue  # PhysGaussian defaults: 0 and 1e3.
      raise ConfigError(
        f'{_where(source, field)} ({kind}): missing field {name!r}.'
      )
  for name, value in bc.items():
    if name == 'type':
      continue
    want = required.get(name, optional.get(name))
    params[name] = _check_kind(source, f'{field}.{name}', value, want)
  if kind == 'surface_collider' and params['surface'] not in SURFACE_TYPES:
    raise ConfigError(
      f'{_where(source, field + ".surface")}: {params["surface"]!r}; '
      f'expected one of {list(SURFACE_TYPES)}.'
    )
  if kind == 'bounding_box' and params and warn:
    logging.warning('%s: %s (bounding_box): start_time/end_time are ignored; '
                    'the domain box is always on (as in PhysGaussian).',
                    source, field)
  # Values that ran with no error and a wrong or no effect.
  for name, ok, want in (
    ('friction', lambda v: v >= 0, 'a Coulomb coefficient >= 0'),
    ('num_dt', lambda v: v >= 1, 'a number of substeps >= 1'),
    ('axis', lambda v: v in (0, 1, 2), '0 (x), 1 (y) or 2 (z)'),
  ):
    if name in params and not ok(params[name]):
      raise ConfigError(f'{_where(source, f"{field}.{name}")} = '
                        f'{params[name]:g}: use {want}.')
  # Values no boundary condition can use (accepted before, then did
  # nothing or failed later without naming the file).
  size = params.get('size')
  if size is not None and not all(s > 0 for s in size):
    raise ConfigError(f'{_where(source, field + ".size")} = {list(size)}: '
                      'give half-extents > 0.')
  start, end = params.get('start_time', 0.0), params.get('end_time', 1e3)
  if end < start:
    raise ConfigError(f'{_where(source, field)}: end_time {end} is before '
                      f'start_time {start}; give end_time >= start_time.')
  normal = params.get('normal')
  if normal is not None and not any(abs(c) > 0 for c in normal):
    raise ConfigError(f'{_where(source, field + ".normal")} = '
                      f'{list(normal)}: give a non-zero vector.')
  return BoundaryCondition(type=kind, params=tuple(sorted(params.items())))


def parse_config(
  raw: dict[str, Any], source: str = '<dict>', warn: bool = True
) -> PhysGaussianConfig:
  """Parses a PhysGaussian JSON dict into a ``PhysGaussianConfig``.

  Args:
    raw: the decoded JSON object.
    source: name used in messages (usually the file path).
    warn: log one line naming present fields that are not honoured.

  Returns:
    The validated, frozen config.

  Raises:
    ConfigError: a field has the wrong type, an unknown name or a value out
      of range; the message names the field, the value and the fix.
  """
  if not isinstance(raw, dict):
    raise ConfigError(
      f'{source}: the config must be a JSON object, got '
      f'{type(raw).__name__}.'
    )
  unknown = sorted(set(raw) - _KNOWN_TOP)
  if unknown:
    near = {k: difflib.get_close_matches(k, sorted(_KNOWN_TOP), n=1)
            for k in unknown}
    hints = ''.join(f'; did you mean {v[0]!r} for {k!r}?'
                    for k, v in near.items() if v)
    logging.warning(
      '%s: ignoring unknown fields %s (not in the PhysGaussian schema%s).',
      source, unknown, hints,
    )
  kw: dict[str, Any] = {'source': source}
  if 'material' in raw:
    kw['material'] = material_name(raw['material'], source)
  for name in ('E', 'nu', 'density', 'grid_lim', 'substep_dt', 'frame_dt',
               'rpic_damping', 'grid_v_damping_scale', 'yield_stress',
               'hardening', 'xi', 'friction_angle', 'plastic_viscosity',
               'softening', 'opacity_threshold', 'scale', 'mu_N', 'lam_N',
               'viscosity'):
    if name in raw:
      kw[name] = _float(source, name, raw[name])
  if kw.get('viscosity') and not kw.get('mu_N'):
    logging.warning(
      '%s: "viscosity" is the viscosity of Physics3D\'s viscoelastic branch, '
      'which needs "mu_N" > 0; without it it is ignored (a fluid\'s '
      'viscosity is "plastic_viscosity").', source)
  for name in ('n_grid', 'frame_num'):
    if name in raw:
      kw[name] = _int(source, name, raw[name])
  if 'g' in raw:
    g = raw['g']
    if isinstance(g, (list, tuple)):
      kw['g'] = _vec(source, 'g', g, 3)
    else:
      kw['g'] = (0.0, 0.0, -_float(source, 'g', g))
  if 'additional_material_params' in raw:
    boxes = raw['additional_material_params']
    if not isinstance(boxes, list):
      raise _type_error(source, 'additional_material_params', boxes, 'a list')
    kw['additional_material_params'] = tuple(
      _parse_box(source, i, b) for i, b in enumerate(boxes)
    )
  if 'boundary_conditions' in raw:
    bcs = raw['boundary_conditions']
    if not isinstance(bcs, list):
      raise _type_error(source, 'boundary_conditions', bcs, 'a list')
    kw['boundary_conditions'] = tuple(
      _parse_bc(source, i, b, warn) for i, b in enumerate(bcs)
    )
  if 'rotation_degree' in raw:
    kw['rotation_degree'] = _vec(source, 'rotation_degree',
                                 raw['rotation_degree'])
  if 'rotation_axis' in raw:
    axes = raw['rotation_axis']
    if not isinstance(axes, list):
      raise _type_error(source, 'rotation_axis', axes, 'a list of 0/1/2')
    kw['rotation_axis'] = tuple(
      _int(source, f'rotation_axis[{i}]', a) for i, a in enumerate(axes)
    )
  if raw.get('sim_area') is not None:
    kw['sim_area'] = _vec(source, 'sim_area', raw['sim_area'], 6)
  if raw.get('particle_filling') is not None:
    pf = raw['particle_filling']
    if not isinstance(pf, dict):
      raise _type_error(source, 'particle_filling', pf, 'an object')
    kw['particle_filling'] = ParticleFilling(params=_freeze(pf))
  cam = {}
  cam_fields = {
    'mpm_space_vertical_upward_axis': ('vertical_upward_axis', 'vec3'),
    'mpm_space_viewpoint_center': ('viewpoint_center', 'vec3'),
    'default_camera_index': ('default_camera_index', 'int'),
    'init_azimuthm': ('init_azimuth', 'float'),
    'init_elevation': ('init_elevation', 'float'),
    'init_radius': ('init_radius', 'float'),
    'delta_a': ('delta_a', 'float'),
    'delta_e': ('delta_e', 'float'),
    'delta_r': ('delta_r', 'float'),
  }
  for name, (attr, kind) in cam_fields.items():
    if raw.get(name) is not None:
      cam[attr] = _check_kind(source, name, raw[name], kind)
  for name in ('move_camera', 'show_hint'):
    if raw.get(name) is not None:
      cam[name] = _bool(source, name, raw[name])
  kw['camera'] = CameraConfig(**cam)
  config = _validate(PhysGaussianConfig(**kw))
  present = [f for f in NOT_HONOURED if raw.get(f) is not None]
  if warn and present:
    logging.warning(
      '%s: fields parsed but not honoured yet (see docs/configs.md): %s',
      source, ', '.join(present),
    )
  partly = [f for f in PARTLY_HONOURED if raw.get(f) is not None]
  if warn and partly:
    logging.warning(
      '%s: fields honoured only in part (see docs/configs.md): %s', source,
      ', '.join(partly),
    )
  return config


def _validate(c: PhysGaussianConfig) -> PhysGaussianConfig:
  s = c.source
  if c.material not in CANONICAL_MODELS:
    material_name(c.material, s)
  if not 0.0 <= c.nu < 0.5:  # (0.5: incompressible, lambda infinite)
    raise ConfigError(
      f'{_where(s, "nu")} = {c.nu!r} is outside [0, 0.5); use a Poisson '
      'ratio in [0, 0.5) (0.3 for most solids, 0.45-0.49 for rubber).'
    )
  for name in ('E', 'density', 'grid_lim', 'substep_dt', 'frame_dt',
               'scale'):
    if getattr(c, name) <= 0:
      raise ConfigError(
        f'{_where(s, name)} = {getattr(c, name)!r} must be > 0.'
      )
  _check_pascals(c.E, _where(s, 'E'))
  for name in ('n_grid', 'frame_num'):
    if getattr(c, name) < 1:
      raise ConfigError(f'{_where(s, name)} = {getattr(c, name)!r} must be'
                        ' >= 1.')
  if c.n_grid < 8:  # (mpm.GridSpec's bound, which named neither)
    raise ConfigError(f'{_where(s, "n_grid")} = {c.n_grid} is too small; '
                      'the quadratic B-spline stencil and the 3-cell domain '
                      'border need n_grid >= 8.')
  if c.substep_dt > c.frame_dt:
    raise ConfigError(
      f'{_where(s, "substep_dt")} = {c.substep_dt} exceeds frame_dt = '
      f'{c.frame_dt}; use substep_dt <= frame_dt.'
    )
  if not 0.0 <= c.rpic_damping <= 1.0:
    raise ConfigError(f'{_where(s, "rpic_damping")} = {c.rpic_damping} must '
                      'be in [0, 1].')
  if not c.grid_v_damping_scale > 0:  # (< 0 flipped the velocities)
    raise ConfigError(
      f'{_where(s, "grid_v_damping_scale")} = {c.grid_v_damping_scale:g}: '
      'use a factor in (0, 1) to damp grid velocities every substep '
      '(PhysGaussian: 0.9999) or >= 1 for no damping.'
    )
  for name in _PLASTICITY_FIELDS:
    check_range(s, name, getattr(c, name))
  for name in ('mu_N', 'viscosity'):
    if not getattr(c, name) >= 0:
      raise ConfigError(f'{_where(s, name)} = {getattr(c, name):g}: use a '
                        f'{"modulus [Pa]" if name == "mu_N" else "viscosity"}'
                        ' >= 0 (Physics3D\'s viscoelastic branch).')
  if c.lam_N and not (c.mu_N > 0 and c.lam_N > 0):
    raise ConfigError(
      f'{_where(s, "lam_N")} = {c.lam_N:g} with mu_N = {c.mu_N:g}: the '
      'viscoelastic branch needs mu_N > 0 and lam_N >= 0 [Pa].')
  if c.mu_N > 0 and c.material not in KELVIN_VOIGT_MODELS:
    raise ConfigError(
      f'{_where(s, "mu_N")} = {c.mu_N:g} on material {c.material!r}: the '
      'viscoelastic branch is for solids (Physics3D gives it to jelly); '
      f'use one of {list(KELVIN_VOIGT_MODELS)} or remove mu_N.')
  if len(c.rotation_degree) != len(c.rotation_axis):
    raise ConfigError(
      f'{s}: rotation_degree has {len(c.rotation_degree)} entries but '
      f'rotation_axis has {len(c.rotation_axis)}; give one axis per angle.'
    )
  for i, a in enumerate(c.rotation_axis):
    if a not in (0, 1, 2):
      raise ConfigError(f'{_where(s, f"rotation_axis[{i}]")} = {a!r}; '
                        'expected 0 (x), 1 (y) or 2 (z).')
  if c.sim_area is not None:
    lo, hi = np.array(c.sim_area[0::2]), np.array(c.sim_area[1::2])
    if np.any(lo >= hi):
      raise ConfigError(f'{_where(s, "sim_area")} = {c.sim_area}: each min '
                        'must be below its max (xmin, xmax, ymin, ...).')
  for i, b in enumerate(c.additional_material_params):
    if not all(v > 0 for v in b.size):  # (had no effect)
      raise ConfigError(
        f'{_where(s, f"additional_material_params[{i}].size")} = '
        f'{list(b.size)}: give half-extents > 0.'
      )
    if b.nu is not None and not 0.0 <= b.nu < 0.5:
      raise ConfigError(
        f'{_where(s, f"additional_material_params[{i}].nu")} = {b.nu} is '
        'outside [0, 0.5); use a Poisson ratio in [0, 0.5).'
      )
    for name in ('E', 'density'):
      v = getattr(b, name)
      if v is not None and v <= 0:
        raise ConfigError(
          f'{_where(s, f"additional_material_params[{i}].{name}")} = {v} '
          'must be > 0.'
        )
    if b.E is not None:
      _check_pascals(b.E, _where(s, f'additional_material_params[{i}].E'))
  return c


def _check_pascals(E: float, where: str) -> None:
  """E below 1 Pa is a config in the units of DreamPhysics, Physics3D or
  PhysFlow, whose solvers multiply E by 1e7 (REFERENCE: units traps):
  read in pascals here it would be a jelly that cannot hold its shape."""
  if E < 1.0:
    raise ConfigError(
      f'{where} = {E!r} Pa is below 1 Pa: a PhysGaussian config gives E in '
      f'pascals (1e4-1e7 for a jelly). A DreamPhysics, Physics3D or PhysFlow '
      f'config gives E / 1e7 (their solvers multiply it by 1e7, PhysFlow '
      f'also yield_stress by 1e5 and plastic_viscosity by 1e4); write the '
      f'pascals, here E = {E * 1e7:.3g}.')


def load_config(path: str | os.PathLike, warn: bool = True
                ) -> PhysGaussianConfig:
  """Reads and parses a PhysGaussian JSON config file.

  Args:
    path: path to the ``.json`` file.
    warn: log fields that are parsed but not honoured.

  Returns:
    The parsed ``PhysGaussianConfig``.

  Raises:
    ConfigError: missing file, a directory, unreadable or non-UTF-8 text,
      invalid JSON or a bad field.
  """
  path = os.fspath(path)
  if os.path.isdir(path):
    try:
      found = sorted(f for f in os.listdir(path) if f.endswith('.json'))
    except OSError:
      found = []
    hint = f' (it holds {", ".join(found[:5])})' if found else ''
    raise ConfigError(f'PhysGaussian config path {path!r} is a directory'
                      f'{hint}; pass the path of the .json config file.')
  if not os.path.isfile(path):
    raise ConfigError(f'PhysGaussian config file {path!r} does not exist; '
                      'give the path of an existing PhysGaussian .json '
                      'config.')
  try:
    with open(path, 'rb') as f:
      data = f.read()
    raw = json.loads(data)  # (UTF-8, with or without BOM, UTF-16/32)
  except OSError as e:
    raise ConfigError(f'{path}: cannot read the config ({e.strerror}); '
                      'check the file and its permissions.') from None
  except UnicodeDecodeError as e:
    line = e.object[:e.start].count(b'\n') + 1
    raise ConfigError(
      f'{path}: not UTF-8 text (byte 0x{e.object[e.start]:02x} on line '
      f'{line}); save the config as UTF-8 JSON.') from None
  except json.JSONDecodeError as e:
    raise ConfigError(f'{path}: invalid JSON ({e}).') from None
  return parse_config(raw, source=path, warn=warn)


# ------------------------------------------------------ arrays and transforms
