"""Constitutive-model names: the canonical names and the aliases users type.

The MPM solver owns these names: PhysGaussian configs, the material library
and MLLM-P3 answers all map onto ``CANONICAL_MODELS``.
"""

from __future__ import annotations

from physsplat_jax.mpm.errors import MPMInputError

CANONICAL_MODELS = (
  'fixed_corotated', 'neo_hookean', 'stvk', 'von_mises', 'drucker_prager',
  'snow', 'foam', 'plasticine', 'newtonian', 'bingham', 'rigid',
)

# PhysGaussian (and PhysDreamer id 6) names and ids -> canonical model names.
MATERIAL_ALIASES = {
  'jelly': 'fixed_corotated', 'elastic': 'fixed_corotated',
  'corotated': 'fixed_corotated', 'metal': 'von_mises',
  'sand': 'drucker_prager',
  'foam': 'foam', 'snow': 'snow', 'plasticine': 'plasticine',
  'neo-hookean': 'neo_hookean', 'neohookean': 'neo_hookean',
  'water': 'newtonian', 'fluid': 'newtonian', 'non_newtonian': 'bingham',
  'non-newtonian': 'bingham',
}
# The parameters beyond (E, nu, rho) each model's update reads
# (mpm.constitutive), in mpm.Materials' units.
# (The solids' 'viscosity' is their Kelvin-Voigt damping, read with
# SimConfig.solid_viscosity, and the maxwell_* fields their Maxwell branch,
# read with SimConfig.maxwell: KELVIN_VOIGT_MODELS.)
_SOLID = ('viscosity', 'maxwell_E', 'maxwell_nu', 'maxwell_viscosity')
MODEL_PARAMS = {
  'fixed_corotated': _SOLID, 'neo_hookean': _SOLID, 'stvk': _SOLID,
  'rigid': (),
  'von_mises': ('yield_stress', 'hardening', 'xi') + _SOLID,
  'plasticine': ('yield_stress', 'hardening', 'xi', 'softening') + _SOLID,
  'drucker_prager': ('friction_angle', 'dp_h1', 'dp_h2', 'dp_h3',
                     'dp_cohesion', 'dp_volume_correction'),
  'snow': ('xi', 'theta_c', 'theta_s') + _SOLID,
  'foam': ('yield_stress', 'plastic_viscosity') + _SOLID,
  'newtonian': ('viscosity',),
  'bingham': ('yield_stress', 'viscosity'),
}
# Solids whose ``viscosity`` adds a Kelvin-Voigt (parallel dashpot) stress
# ``J eta (C + C^T - 2/3 tr(C) I)`` when ``SimConfig.solid_viscosity`` is
# on (mpm.constitutive). The fluids read ``viscosity`` themselves; sand
# takes none (a dashpot would carry shear and tension outside its cone).
KELVIN_VOIGT_MODELS = (
  'fixed_corotated', 'neo_hookean', 'stvk', 'von_mises', 'plasticine',
  'snow', 'foam',
)

# The physical ranges of those parameters: (test, what to use). A value
# outside was accepted and blew up a frame later, blamed on the time step;
# perception's overrides and PhysGaussian configs check against these.
PARAM_RANGES = {
  'friction_angle': (lambda v: 0.0 <= v < 90.0, 'an angle in [0, 90) deg'),
  'yield_stress': (lambda v: v >= 0.0, 'a stress >= 0 [Pa]'),
  'viscosity': (lambda v: v >= 0.0, 'a viscosity >= 0 [Pa s]'),
  'plastic_viscosity': (lambda v: v >= 0.0, 'a viscosity >= 0 [Pa s]'),
  'hardening': (lambda v: v >= 0.0, '0 (off) or a multiplier > 0'),
  'xi': (lambda v: 0.0 <= v <= 100.0, 'a hardening coefficient in '
         '[0, 100] (snow: ~10)'),
  'softening': (lambda v: v >= 0.0, 'a softening >= 0 [Pa]'),
  'theta_c': (lambda v: 0.0 < v < 1.0, 'a critical compression in (0, 1)'),
  'theta_s': (lambda v: 0.0 < v < 1.0, 'a critical stretch in (0, 1)'),
  'dp_cohesion': (lambda v: v >= 0.0, 'a cohesion strain >= 0'),
  'dp_volume_correction': (lambda v: v in (0.0, 1.0), '0 or 1'),
  'maxwell_E': (lambda v: v >= 0.0, "a Young's modulus >= 0 [Pa]"),
  'maxwell_nu': (lambda v: 0.0 <= v < 0.5, "a Poisson's ratio in [0, 0.5)"),
  'maxwell_viscosity': (lambda v: v >= 0.0, 'a viscosity >= 0 [Pa s]'),
}

MATERIAL_IDS = {
  0: 'fixed_corotated', 1: 'von_mises', 2: 'drucker_prager', 3: 'foam',
  4: 'snow', 5: 'plasticine', 6: 'neo_hookean',
}


def canonical_model(value) -> str | None:
  """A canonical model name from a name, alias or PhysGaussian id, or None.

  Args:
    value: 'jelly', 'sand', 2, 'neo-hookean', 'stvk', ... (case-insensitive).
  """
  if isinstance(value, bool):
    return None
  if isinstance(value, (int, float)) and float(value).is_integer():
    return MATERIAL_IDS.get(int(value))
  if not isinstance(value, str):
    return None
  key = value.strip().lower()
  if key in CANONICAL_MODELS:
    return key
  return MATERIAL_ALIASES.get(key)


# The Maxwell (viscoelastic) branch's fields of mpm.Materials, None unless
# given (SimConfig.maxwell): its Young's modulus and Poisson ratio (Hencky
# spring) and the viscosity of its dashpot.
MAXWELL_FIELDS = ('maxwell_E', 'maxwell_nu', 'maxwell_viscosity')

# Defaults per model for the fields beyond (E, nu, rho). Sources: PhysGaussian
# (mpm_solver_warp defaults: softening 0.1, friction angle 25 deg, plastic
# viscosity 0); Stomakhin et al. 2013 (snow: xi 10, theta_c 2.5e-2,
# theta_s 7.5e-3); Klar et al. 2016 (h2 = 0.2); water (1e-3 Pa s); bingham:
# PhysFlow's jam (J2 50 Pa, 200 Pa s) in shear terms, 50/sqrt(3) and 200/2.
_GENERIC = dict(
  yield_stress=1e4, hardening=0.0, xi=0.0, softening=0.0,
  friction_angle=25.0, dp_h1=0.0, dp_h2=0.2, dp_h3=0.0,
  plastic_viscosity=0.0, viscosity=0.0, theta_c=2.5e-2, theta_s=7.5e-3,
  dp_cohesion=0.0, dp_volume_correction=1.0,
  maxwell_E=0.0, maxwell_nu=0.3, maxwell_viscosity=0.0,
)
MODEL_DEFAULTS = {
  'fixed_corotated': {},
  'neo_hookean': {},
  'stvk': {},
  'von_mises': dict(yield_stress=1e4),
  'drucker_prager': dict(friction_angle=25.0),
  'snow': dict(xi=10.0),
  'foam': dict(yield_stress=1e2, plastic_viscosity=0.0),
  'plasticine': dict(yield_stress=1e3, softening=0.1),
  'newtonian': dict(viscosity=1e-3),
  'bingham': dict(yield_stress=28.9, viscosity=100.0),
  'rigid': {},
}


def model_default(model: str, field: str) -> float:
  """Default value of a ``Materials`` field (one of ``FLOAT_FIELDS[3:]``;
  E, nu, rho have none) for a canonical model (``MODEL_DEFAULTS``); raises
  ``MPMInputError`` (a ValueError) for an unknown model or field."""
  if model not in MODEL_DEFAULTS:
    raise MPMInputError(f'model_default: unknown model {model!r}.')
  if field not in _GENERIC:
    raise MPMInputError(f'model_default: {field!r} has no default; fields with '
                        f'defaults are {list(_GENERIC)}.')
  return MODEL_DEFAULTS[model].get(field, _GENERIC[field])
