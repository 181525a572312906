"""Tests of the material library: schema, physics, preset law, lookup."""

import copy
import json
import math
import os
import tempfile

from absl.testing import absltest
from absl.testing import parameterized

from physsplat_jax.physgaussian import CANONICAL_MODELS
from physsplat_jax.perception import library as lib

# The preset values are rounded to 2 significant digits.
_ROUNDING_RTOL = 0.05
# Keys that the built-in scenes use.
_SCENE_KEYS = ('terracotta', 'soil', 'plant_stem', 'leaf', 'wood', 'jelly',
               'rubber', 'sand', 'aluminum', 'dough')


def _raw():
  path = os.path.join(os.path.dirname(lib.__file__), '..', 'data',
                      'materials.json')
  with open(path, encoding='utf-8') as f:
    return json.load(f)


class ShippedLibraryTest(parameterized.TestCase):

  def setUp(self):
    super().setUp()
    self.L = lib.default_library()

  def test_size_and_required_keys(self):
    self.assertGreaterEqual(len(self.L), 40)
    for k in _SCENE_KEYS:
      self.assertIn(k, self.L)

  def test_every_model_is_canonical_and_covered(self):
    models = {e.model for e in self.L.entries}
    self.assertTrue(models <= set(CANONICAL_MODELS), models)
    # Every non-rigid constitutive family has at least one material.
    for m in ('fixed_corotated', 'neo_hookean', 'stvk', 'von_mises',
              'drucker_prager', 'snow', 'foam', 'plasticine', 'newtonian',
              'bingham'):
      self.assertIn(m, models)

  def test_every_parameter_is_read_by_its_model(self):
    # A Bingham fluid's 'plastic_viscosity' and snow's 'hardening' were
    # ignored by the solver (it reads 'viscosity' and 'xi'): ketchup
    # flowed at the default 200 Pa s instead of its 0.5 Pa s.
    from physsplat_jax.mpm.models import MODEL_PARAMS as SOLVER_PARAMS
    for model, params in lib.MODEL_PARAMS.items():
      self.assertLessEqual(set(params), set(SOLVER_PARAMS[model]), model)
    for e in self.L.entries:
      read = set(SOLVER_PARAMS[e.model])
      self.assertLessEqual(set(dict(e.params)), read, e.key)
    self.assertEqual(dict(self.L['ketchup'].params)['viscosity'], 0.5)

  def test_physical_sanity(self):
    for e in self.L.entries:
      with self.subTest(key=e.key):
        for r in (e.density, e.youngs_modulus, e.poisson_ratio):
          self.assertLessEqual(r.min, r.max)
        self.assertGreater(e.density.min, 0.0)
        self.assertGreater(e.youngs_modulus.min, 0.0)
        self.assertGreaterEqual(e.poisson_ratio.min, 0.0)
        self.assertLess(e.poisson_ratio.max, 0.5)
        # Densities between aerogel-light foams and lead.
        self.assertBetween(e.density.min, 5.0, 2e4)
        self.assertBetween(e.density.max, 5.0, 2e4)
        self.assertBetween(e.youngs_modulus.max, 1e2, 1e12)
        self.assertTrue(e.sources)
        for s in e.sources:
          self.assertIn(s, self.L.sources_dict)
        for p in lib.MODEL_PARAMS[e.model]:
          self.assertIn(p, e.params_dict)
          self.assertTrue(math.isfinite(e.params_dict[p]))
          self.assertGreaterEqual(e.params_dict[p], 0.0)
        if e.model == 'drucker_prager':
          self.assertBetween(e.params_dict['friction_angle'], 10.0, 60.0)
        if e.model == 'snow':
          self.assertLess(e.params_dict['theta_s'], e.params_dict['theta_c'])

  def test_rigid_flags(self):
    for e in self.L.entries:
      with self.subTest(key=e.key):
        if e.rigid:
          # Only materials far too stiff for video-rate time steps.
          self.assertGreaterEqual(e.youngs_modulus.min, 1e8)
          self.assertNotIn(e.model, lib.NEVER_RIGID_MODELS)
    for k in ('aluminum', 'wood', 'terracotta', 'steel', 'glass'):
      self.assertTrue(self.L[k].rigid, k)
    for k in ('jelly', 'rubber', 'sand', 'soil', 'leaf', 'plant_stem',
              'dough'):
      self.assertFalse(self.L[k].rigid, k)

  def test_preset_law(self):
    e_ref = self.L.E_reference
    lo, hi = self.L.E_sim_bounds
    self.assertEqual((e_ref, lo, hi), (1e5, 1e3, 1e7))
    for e in self.L.entries:
      with self.subTest(key=e.key):
        law = min(max(math.sqrt(e.E_mid * e_ref), lo), hi)
        self.assertAlmostEqual(e.E_sim / law, 1.0, delta=_ROUNDING_RTOL)
        self.assertBetween(e.E_sim, lo, hi)
        nu = min(e.poisson_ratio.mid, self.L.nu_sim_max)
        self.assertAlmostEqual(e.nu_sim, nu, delta=1e-3)
        self.assertLess(e.nu_sim, 0.5)
        self.assertTrue(e.density.contains(e.rho_sim))
        self.assertAlmostEqual(e.rho_sim / e.density.geometric_mid, 1.0,
                               delta=_ROUNDING_RTOL)
        # The rule's plastic parameters (preset_rule), exactly: the choice
        # recomputes them from E (choice.params_at), and an estimate equal
        # to the library's mid value must give the preset.
        if e.model in lib.STRAIN_YIELD_MODELS:
          self.assertIsNotNone(e.yield_strain)
          self.assertAlmostEqual(
            e.params_dict['yield_stress'] / (e.yield_strain * e.E_sim), 1.0,
            delta=1e-9)
        if e.model == 'foam':  # relaxation time 0.01 s
          self.assertAlmostEqual(
            e.params_dict['plastic_viscosity'] / (0.01 * e.E_sim), 1.0,
            delta=1e-9)
        if e.model == 'plasticine':  # no damage (see preset_rule)
          self.assertEqual(e.params_dict['softening'], 0.0)

  def test_plastic_parameters_follow_a_rescaled_E(self):
    """An estimate 4x the entry's mid modulus doubles E_sim (the law's
    exponent 0.5); the foam's yield stress and plastic viscosity double
    with it (same yield strain and relaxation time), its mid value gives
    the preset's own parameters."""
    from physsplat_jax.perception import choice  # noqa: PLC0415
    e = self.L['foam']
    for factor, scale in ((1.0, 1.0), (4.0, 2.0)):
      E, _, _, params = choice.simulation_values(
        e, self.L, factor * e.E_mid, 0.2, 40.0)
      self.assertAlmostEqual(E / e.E_sim, scale, delta=1e-9)
      for k in ('yield_stress', 'plastic_viscosity'):
        self.assertAlmostEqual(dict(params)[k] / e.params_dict[k], scale,
                               delta=1e-9, msg=k)

  def test_preset_keeps_stiffness_order(self):
    es = sorted(self.L.entries, key=lambda e: e.E_mid)
    for a, b in zip(es, es[1:]):
      self.assertLessEqual(a.E_sim, b.E_sim * (1 + _ROUNDING_RTOL),
                           f'{a.key} vs {b.key}')

  def test_fluid_moduli_follow_bulk_modulus(self):
    for e in self.L.entries:
      if e.model not in ('newtonian', 'bingham'):
        continue
      with self.subTest(key=e.key):
        K = e.bulk_modulus
        self.assertIsNotNone(K)
        nu = e.poisson_ratio
        self.assertAlmostEqual(
          e.youngs_modulus.min / (3 * K.min * (1 - 2 * nu.max)), 1.0,
          delta=_ROUNDING_RTOL)

  @parameterized.named_parameters(
    ('metal_can', 'metal can', 'aluminum'),
    ('rubber_ball', 'rubber ball', 'rubber'),
    ('jelly_cube', 'jelly cube', 'jelly'),
    ('ficus_leaves', 'ficus leaves', 'leaf'),
    ('key', 'plant_stem', 'plant_stem'),
    ('key_spaces', 'Plant Stem', 'plant_stem'),
    ('alias', 'aluminium', 'aluminum'),
    ('plural', 'Leaves', 'leaf'),
    ('wooden_table', 'wooden table', 'wood'),
    ('material_beats_object', 'soil in pot', 'soil'),
    ('clay_pot', 'clay pot', 'terracotta'),
    ('sand_pile', 'sand pile', 'sand'),
    ('typo', 'alumnium', 'aluminum'),
    ('keyword', 'teddy bear', 'foam'),
    ('cast_iron', 'cast iron pan', 'cast_iron'),
    ('dough_ball', 'ball of dough', 'dough'),
  )
  def test_lookup(self, name, key):
    self.assertEqual(self.L.lookup(name).key, key)

  def test_no_match(self):
    self.assertIsNone(self.L.match('xyzzy qwerty'))
    with self.assertRaisesRegex(lib.MaterialNotFoundError,
                                r"'xyzzy qwerty'.*override"):
      self.L.lookup('xyzzy qwerty')
    m = self.L.lookup('xyzzy qwerty', default='jelly')
    self.assertEqual((m.key, m.how), ('jelly', 'default'))
    with self.assertRaisesRegex(lib.MaterialNotFoundError, 'nonsense_key'):
      self.L.lookup('xyzzy', default='nonsense_key')
    with self.assertRaisesRegex(lib.MaterialNotFoundError, 'close keys'):
      self.L['alumium']

  def test_similarity(self):
    s = self.L.similarity('a shiny silver drink can made of thin metal')
    self.assertEqual(max(s, key=s.get), 'aluminum')
    s = self.L.similarity('a wobbly translucent green dessert cube')
    self.assertEqual(max(s, key=s.get), 'jelly')
    self.assertTrue(all(0.0 <= v <= 1.0 + 1e-9 for v in s.values()))
    self.assertEqual(set(self.L.similarity('zzz').values()), {0.0})


class ParseErrorTest(parameterized.TestCase):

  def _bad(self, mutate, pattern):
    data = copy.deepcopy(_raw())
    mutate(data)
    with self.assertRaisesRegex(lib.LibraryError, pattern):
      lib.parse_library(data, origin='bad.json')

  def test_nu_out_of_range(self):
    def m(d):
      d['materials']['jelly']['poisson_ratio'] = {'min': 0.3, 'max': 0.7}
    self._bad(m, r'bad.json: materials.jelly.poisson_ratio.*\[0, 0.5\)')

  def test_unordered_range(self):
    def m(d):
      d['materials']['wood']['density'] = {'min': 900, 'max': 400}
    self._bad(m, r'materials.wood.density.*min <= max')

  def test_unknown_model(self):
    def m(d):
      d['materials']['sand']['model'] = 'granular'
    self._bad(m, r"materials.sand.model = 'granular'")

  def test_missing_param(self):
    def m(d):
      del d['materials']['sand']['params']['friction_angle']
    self._bad(m, r"materials.sand.params lacks \['friction_angle'\]")

  def test_duplicate_alias(self):
    def m(d):
      d['materials']['steel']['aliases'].append('aluminium')
    self._bad(m, r"'aluminium' of materials.steel is already "
              r'.*materials.aluminum')

  def test_unknown_source(self):
    def m(d):
      d['materials']['steel']['sources'] = ['my_blog']
    self._bad(m, r"materials.steel.sources \['my_blog'\]")

  def test_load_file(self):
    with tempfile.TemporaryDirectory() as d:
      p = os.path.join(d, 'm.json')
      with open(p, 'w') as f:
        json.dump(_raw(), f)
      self.assertEqual(len(lib.load_library(p)), len(lib.default_library()))
      with open(p, 'w') as f:
        f.write('{"materials": ')
      with self.assertRaisesRegex(lib.LibraryError, r'm.json: invalid JSON'):
        lib.load_library(p)
      with self.assertRaisesRegex(lib.LibraryError, 'cannot read'):
        lib.load_library(os.path.join(d, 'missing.json'))


if __name__ == '__main__':
  absltest.main()
