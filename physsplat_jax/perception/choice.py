"""Material choices: the per-object result of perception, and how values map
to the simulation preset.

Mapping a real-world estimate to simulation values (docs/materials.md)::

  ratio  = clip(E_real / E_mid, 1 / R, R)           R = max_E_ratio (100)
  E_sim  = clip(E_sim_lib * ratio ** 0.5, E_sim_min, E_sim_max)
  nu_sim = min(nu_real, nu_sim_max)                  (0.45)
  rho_sim = rho_real
  yield_stress = yield_strain * E_sim                (strain-yield models)
  plastic_viscosity *= E_sim / E_sim_lib             (foam)

``E_mid`` is the library entry's real mid-range modulus and ``E_sim_lib`` its
preset. The exponent 0.5 is the library's own compression law
(``E_sim = sqrt(E_mid * 1e5 Pa)``), so an estimate equal to the library's
mid value gives exactly the preset, and an estimate 100x stiffer gives a 10x
stiffer simulation at most. ``nu`` is capped because the bulk modulus
``E / (3 (1 - 2 nu))`` (and with it the stable time step) diverges as nu ->
0.5.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

from absl import logging

from physsplat_jax.errors import PhysSplatError
from physsplat_jax.mpm.models import CANONICAL_MODELS
from physsplat_jax.mpm.models import MAXWELL_FIELDS
from physsplat_jax.mpm.models import PARAM_RANGES
from physsplat_jax.mpm.models import canonical_model
from physsplat_jax.mpm.models import MODEL_PARAMS as SOLVER_PARAMS
from physsplat_jax.perception.library import MODEL_PARAMS
from physsplat_jax.perception.library import NEVER_RIGID_MODELS
from physsplat_jax.perception.library import STRAIN_YIELD_MODELS
from physsplat_jax.perception.library import MaterialEntry
from physsplat_jax.perception.library import MaterialLibrary

SOURCES = ('mllm', 'library', 'config', 'override')
_SPEC_FIELDS = {'material', 'key', 'model', 'E', 'nu', 'rho', 'density',
                'rigid'}
# (The library's parameters, and a solid's Maxwell branch.)
_ALL_PARAMS = sorted({p for ps in MODEL_PARAMS.values() for p in ps}
                     | set(MAXWELL_FIELDS))
# Names of the same spec field: give one.
_SPEC_ALIASES = (('material', 'key'), ('rho', 'density'))


def model_params(model: str) -> tuple[str, ...]:
  """The parameters an override may set for ``model``: the library's, and
  the others of ``_ALL_PARAMS`` the solver's update reads for it."""
  lib = tuple(MODEL_PARAMS.get(model, ()))
  return lib + tuple(p for p in SOLVER_PARAMS.get(model, ())
                     if p in _ALL_PARAMS and p not in lib)


@dataclasses.dataclass(frozen=True)
class ObjectMaterial:
  """The material of one object: the one record that perception produces
  and the pipeline consumes (hashable).

  Attributes:
    model: constitutive model (``CANONICAL_MODELS``); for a rigid object,
      the model it would be simulated with as a deformable body.
    E: Young's modulus to simulate with [Pa] (the simulation value).
    nu: Poisson's ratio to simulate with, in [0, 0.5).
    rho: density to simulate with [kg/m^3].
    rigid: simulate as a rigid body.
    params: model parameters in simulation units, sorted ``(name, value)``
      (e.g. yield_stress).
    material_key: the library key, or ''.
    source: 'mllm', 'library', 'config' or 'override': which path chose it.
    reason: one line saying why.
    object_name: the scene object's name ('' when given directly).
    E_real: the real-world Young's modulus estimate [Pa] behind ``E`` (the
      MLLM's validated answer or the library's mid value), or None when the
      values were given directly (config/override).
    caption: the MLLM's caption ('' offline).
    candidates: the MLLM's candidate keys, best first (() offline).
    warnings: what went wrong on the way (empty when nothing did).
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
  object_name: str = ''
  E_real: float | None = None
  caption: str = ''
  candidates: tuple[str, ...] = ()
  warnings: tuple[str, ...] = ()

  @property
  def params_dict(self) -> dict[str, float]:
    return dict(self.params)

  def to_dict(self) -> dict[str, Any]:
    """JSON-ready dict (for report.json)."""
    d = dataclasses.asdict(self)
    d['params'] = self.params_dict
    d['candidates'] = list(self.candidates)
    d['warnings'] = list(self.warnings)
    return d

  def summary(self) -> str:
    """``key [model, rigid] E=.. nu=.. rho=..`` for log lines."""
    kind = 'rigid' if self.rigid else 'deformable'
    return (f'{self.material_key} [{self.model}, {kind}] E_sim={self.E:.3g} '
            f'Pa nu={self.nu:.3g} rho={self.rho:.4g} kg/m^3')


class MaterialChoiceError(PhysSplatError, ValueError):
  """A material override or config value is malformed, unknown or
  unphysical; the message names the object and the field."""


# The name perception has always used for the same record.
MaterialChoice = ObjectMaterial


def check_choice(c: MaterialChoice) -> MaterialChoice:
  """Returns ``c`` or raises :class:`MaterialChoiceError` if any value is
  unphysical."""
  bad = []
  if c.model not in CANONICAL_MODELS:
    bad.append(f'model {c.model!r} not in {list(CANONICAL_MODELS)}')
  if not (math.isfinite(c.E) and c.E > 0):
    bad.append(f"E={c.E} (use a Young's modulus > 0 [Pa])")
  if not (math.isfinite(c.nu) and 0.0 <= c.nu < 0.5):
    bad.append(f"nu={c.nu} (use a Poisson's ratio in [0, 0.5))")
  if not (math.isfinite(c.rho) and c.rho > 0):
    bad.append(f'rho={c.rho} (use a density > 0 [kg/m^3])')
  if c.source not in SOURCES:
    bad.append(f'source {c.source!r}')
  for k, v in c.params:
    if not math.isfinite(v):
      bad.append(f'param {k}={v}')
    elif k in PARAM_RANGES and not PARAM_RANGES[k][0](v):
      bad.append(f'{k}={v} (use {PARAM_RANGES[k][1]})')
  if bad:
    raise MaterialChoiceError(f'material of object {c.object_name!r}: invalid '
                              + ', '.join(bad))
  return c


def simulation_values(
  entry: MaterialEntry,
  library: MaterialLibrary,
  E_real: float,
  nu_real: float,
  rho_real: float,
  max_E_ratio: float = 100.0,
) -> tuple[float, float, float, tuple[tuple[str, float], ...]]:
  """Maps real-world estimates to simulation values (module docstring).

  Args:
    entry: the library material.
    library: for the preset bounds.
    E_real, nu_real, rho_real: validated real-world estimates [Pa, 1,
      kg/m^3].
    max_E_ratio: R, the largest factor between ``E_real`` and the entry's
      mid value that is honoured.

  Returns:
    ``(E_sim, nu_sim, rho_sim, params)``.
  """
  lo, hi = library.E_sim_bounds
  ratio = min(max(E_real / entry.E_mid, 1.0 / max_E_ratio), max_E_ratio)
  E_sim = min(max(entry.E_sim * math.sqrt(ratio), lo), hi)
  nu_sim = min(float(nu_real), library.nu_sim_max)
  params = params_at(entry, E_sim)
  return float(E_sim), float(nu_sim), float(rho_real), tuple(
    sorted(params.items()))


def params_at(entry: MaterialEntry, E_sim: float) -> dict[str, float]:
  """The entry's model parameters for a simulated modulus ``E_sim``.

  Those the library ties to E follow it: a strain-yield model's
  ``yield_stress = yield_strain * E_sim`` (the same yield strain) and a
  foam's ``plastic_viscosity`` in proportion (the same relaxation time);
  the others are real values (docs/materials.md).
  """
  params = dict(entry.params)
  if entry.model in STRAIN_YIELD_MODELS and entry.yield_strain is not None:
    params['yield_stress'] = entry.yield_strain * E_sim
  if 'plastic_viscosity' in params and entry.E_sim > 0:
    params['plastic_viscosity'] *= E_sim / entry.E_sim
  return params


def choice_from_entry(
  object_name: str,
  entry: MaterialEntry,
  source: str,
  reason: str,
  warnings=(),
) -> MaterialChoice:
  """The entry's simulation preset, as a choice."""
  return check_choice(MaterialChoice(
    object_name=object_name, material_key=entry.key, model=entry.model,
    E=entry.E_sim, nu=entry.nu_sim, rho=entry.rho_sim, rigid=entry.rigid,
    params=entry.params, source=source, reason=reason, E_real=entry.E_mid,
    warnings=tuple(warnings),
  ))


def rigid_for(entry: MaterialEntry, rigid: bool | None,
              object_name: str = '') -> tuple[bool, str]:
  """The rigid flag to use given a model's answer, and a note ('' if none).

  Granular media and fluids (``NEVER_RIGID_MODELS``) are never rigid. A
  rigid answer for a material the library simulates as deformable (jelly,
  rubber) is kept, with a note naming the object and the library's value.
  """
  if rigid is None:
    return entry.rigid, ''
  if rigid and entry.model in NEVER_RIGID_MODELS:
    return False, (f'rigid=true ignored: {entry.key} ({entry.model}) '
                   'cannot be a rigid body')
  if rigid and not entry.rigid:
    return True, (
      f'object {object_name!r}: the MLLM says rigid=true but the library '
      f'simulates {entry.key} as deformable (rigid=false, {entry.model}); '
      "kept the MLLM's answer (override: "
      f'{object_name}={{"material": "{entry.key}", "rigid": false}})')
  return bool(rigid), ''


def _some_keys(library: MaterialLibrary, name: str) -> str:
  """Library keys to show in a message: those close to ``name``, else a
  spread of the library's."""
  keys = library.suggest(name) or list(library.keys[::11])
  return ', '.join(map(repr, keys))


def _all_keys(library: MaterialLibrary) -> str:
  """Where a message's reader finds every key."""
  return (f'all {len(library)}: physsplat_jax.perception.default_library()'
          '.keys, docs/materials.md')


def apply_spec(
  object_name: str,
  spec: Any,
  library: MaterialLibrary,
  base: MaterialEntry | None,
  source: str,
) -> MaterialChoice:
  """A choice from an override or config value.

  Args:
    object_name: the object's name.
    spec: a library key or name (``'rubber'``, ``'rubber ball'``), or a
      mapping with any of ``material`` (key or name), ``model``, ``E``,
      ``nu``, ``rho`` (or ``density``), ``rigid`` and model parameters
      (``yield_stress``, ``friction_angle``, ...). Numbers are SIMULATION
      values, used as given (E in Pa as the solver sees it).
    library: the material library.
    base: the entry to start from when the mapping names no material (e.g.
      the one the object's name matches); None requires ``material``.
    source: 'override' or 'config'.

  Returns:
    A validated :class:`MaterialChoice`.

  Raises:
    MaterialChoiceError: unknown material, unknown field, or unphysical
      value; the message names the object and the field.
  """
  where = f'{source} for object {object_name!r}'
  if isinstance(spec, str):
    spec = {'material': spec}
  if not isinstance(spec, Mapping):
    raise MaterialChoiceError(
      f'{where}: expected a material key or a mapping, got '
      f'{spec!r}')
  unknown = sorted(set(spec) - _SPEC_FIELDS - set(_ALL_PARAMS))
  if unknown:
    raise MaterialChoiceError(
      f'{where}: unknown field(s) {unknown}; allowed: '
      f'{sorted(_SPEC_FIELDS)} and parameters {_ALL_PARAMS}')
  for a, b in _SPEC_ALIASES:
    if a in spec and b in spec:
      raise MaterialChoiceError(
        f'{where}: both {a!r} ({spec[a]!r}) and {b!r} ({spec[b]!r}) are '
        'given; they name the same field: give one')
  name = spec.get('material', spec.get('key'))
  if name is not None:
    m = library.match(str(name))
    if m is None or m.how == 'fuzzy':
      # A material the user names is taken as written: a close spelling is
      # offered, never substituted (a typo's nearest key may be another
      # material).
      fix = (f'did you mean {m.key!r}? Write the key exactly (a close '
             'spelling is not taken for it)' if m is not None else
             f'give a library key or alias, such as '
             f'{_some_keys(library, str(name))}')
      raise MaterialChoiceError(
        f'{where}: material {name!r} is not in the library; {fix} '
        f'({_all_keys(library)})')
    entry = library[m.key]
    how = f'{name!r}' if m.key == name else f'{name!r} -> {m.key}'
  elif base is not None:
    entry, how = base, f'values over {base.key}'
  else:
    raise MaterialChoiceError(
      f'{where}: no "material" given and the object name '
      'matches no library material; add "material": KEY to the mapping, '
      f'KEY a library key such as {_some_keys(library, object_name)} '
      f'({_all_keys(library)})')
  fields = {'E': entry.E_sim, 'nu': entry.nu_sim, 'rho': entry.rho_sim}
  for k_spec, k in (('E', 'E'), ('nu', 'nu'), ('rho', 'rho'),
                    ('density', 'rho')):
    if k_spec in spec:
      try:
        fields[k] = float(spec[k_spec])
      except (TypeError, ValueError):
        raise MaterialChoiceError(
          f'{where}: {k_spec}={spec[k_spec]!r} is not a '
          'number') from None
  model = spec.get('model', entry.model)
  if model not in CANONICAL_MODELS:
    resolved = canonical_model(model)
    if resolved is None:
      raise MaterialChoiceError(f'{where}: model {model!r} is not one of '
                                f'{list(CANONICAL_MODELS)}')
    model = resolved
  rigid = spec.get('rigid', entry.rigid)
  if not isinstance(rigid, bool):
    raise MaterialChoiceError(f'{where}: rigid={rigid!r} must be true or false')
  params = params_at(entry, fields['E']) if model == entry.model else {}
  takes = model_params(model)
  extra = sorted(p for p in spec if p in _ALL_PARAMS and p not in takes)
  if extra:
    raise MaterialChoiceError(
      f'{where}: model {model!r} ({entry.key}) takes no parameter(s) '
      f'{extra}; its parameters: {list(takes) or "none"} (set "model" to '
      'one that takes them)')
  for p in _ALL_PARAMS:
    if p in spec:
      try:
        params[p] = float(spec[p])
      except (TypeError, ValueError):
        raise MaterialChoiceError(f'{where}: {p}={spec[p]!r} is not a number'
                                  ) from None
  if model == 'foam' and 'viscosity' in spec and (
      'plastic_viscosity' not in spec):
    logging.warning(
      '%s: "viscosity" on a foam is a Kelvin-Voigt dashpot beside its flow; '
      'its flow\'s viscosity is "plastic_viscosity" (docs/mpm.md)', where)
  missing = [p for p in MODEL_PARAMS[model] if p not in params]
  if missing:
    raise MaterialChoiceError(f'{where}: model {model!r} needs parameter(s) '
                              f'{missing}')
  given = sorted(k for k in spec if k not in ('material', 'key'))
  reason = f'{source} {how}' + (f' with {given}' if given else '')
  try:
    return check_choice(MaterialChoice(
      object_name=object_name, material_key=entry.key, model=model,
      E=fields['E'], nu=fields['nu'], rho=fields['rho'], rigid=rigid,
      params=tuple(sorted(params.items())), source=source, reason=reason,
      E_real=None if given else entry.E_mid,
    ))
  except MaterialChoiceError as e:
    raise MaterialChoiceError(f'{where}: {e}') from None


# A representative library key per constitutive model (for labelling a
# PhysGaussian config's single material).
MODEL_KEYS = {
  'fixed_corotated': 'jelly', 'neo_hookean': 'rubber', 'stvk': 'fabric',
  'von_mises': 'sheet_metal', 'drucker_prager': 'sand', 'snow': 'snow',
  'foam': 'foam', 'plasticine': 'plasticine', 'newtonian': 'water',
  'bingham': 'ketchup', 'rigid': 'wood',
}


def spec_from_physgaussian(config) -> dict[str, Any]:
  """A config-material spec (for ``PerceptionOptions.config_materials``)
  from a PhysGaussian config: its model, E, nu, density and the plasticity
  parameters that model uses, labelled with a representative library key.

  Args:
    config: a :class:`~physsplat_jax.physgaussian.PhysGaussianConfig`.

  Returns:
    ``{'material': key, 'model': ..., 'E': ..., 'nu': ..., 'rho': ...,
    <params>}``; use as ``config_materials={'*': spec}``.
  """
  model = config.material
  spec: dict[str, Any] = {
    'material': MODEL_KEYS.get(model, 'jelly'), 'model': model,
    'E': float(config.E), 'nu': float(config.nu),
    'rho': float(config.density), 'rigid': model == 'rigid',
  }
  # PhysGaussian's snow has no parameters of its own (its 'hardening' is the
  # von Mises one): keep the library's Stomakhin values.
  for p in MODEL_PARAMS.get(model, ()) if model != 'snow' else ():
    # A config's fluid viscosity is its plastic_viscosity, as the
    # PhysGaussian driver reads it (0: the model's default; docs/configs.md).
    src = 'plastic_viscosity' if p == 'viscosity' else p
    value = getattr(config, src, None)
    if value is not None and (value or p != 'viscosity'):
      spec[p] = float(value)
  spec.update(config.maxwell_params)  # Physics3D's viscoelastic branch
  return spec
