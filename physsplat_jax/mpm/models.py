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
  'corotated': 'fixed_corotated', 'metal': 'von_mises', 'sand': 'drucker_prager',
  'foam': 'foam', 'snow': 'snow', 'plasticine': 'plasticine',
  'neo-hookean': 'neo_hookean', 'neohookean': 'neo_hookean',
  'water': 'newtonian', 'fluid': 'newtonian', 'non_newtonian': 'bingham',
  'non-newtonian': 'bingham',
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
