"""Constitutive-model names: the canonical names and the aliases users type.

The MPM solver owns these names: PhysGaussian configs, the material library
and MLLM-P3 answers all map onto ``CANONICAL_MODELS``.
"""

from __future__ import annotations

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
# (The solids' 'viscosity', last, is their Kelvin-Voigt damping: read with
# SimConfig.solid_viscosity, KELVIN_VOIGT_MODELS.)
MODEL_PARAMS = {
  'fixed_corotated': ('viscosity',), 'neo_hookean': ('viscosity',),
  'stvk': ('viscosity',), 'rigid': (),
  'von_mises': ('yield_stress', 'hardening', 'xi', 'viscosity'),
  'plasticine': ('yield_stress', 'hardening', 'xi', 'softening',
                 'viscosity'),
  'drucker_prager': ('friction_angle', 'dp_h1', 'dp_h2', 'dp_h3',
                     'dp_cohesion', 'dp_volume_correction'),
  'snow': ('xi', 'theta_c', 'theta_s', 'viscosity'),
  'foam': ('yield_stress', 'plastic_viscosity', 'viscosity'),
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
