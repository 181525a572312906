"""Tests for physsplat_jax.physgaussian (PhysGaussian JSON schema)."""

import json
import os
import re
import tempfile
import types

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest
from absl.testing import parameterized

from physsplat_jax import physgaussian as pg

_REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_EXAMPLES = os.path.join(_REPO, 'experiments', 'configs')

# REFERENCE.md §1.2: PhysGaussian ficus (jelly), wolf (sand), plane (metal).
_FICUS = {
  'material': 'jelly', 'E': 2e6, 'nu': 0.4, 'density': 200, 'g': [0, 0, 0],
  'substep_dt': 1e-4, 'frame_dt': 4e-2, 'frame_num': 125,
  'grid_v_damping_scale': 0.9999, 'rpic_damping': 0.0,
  'additional_material_params': [
    {'point': [1, 1, 1.36], 'size': [0.5, 0.5, 0.3], 'E': 2e6, 'nu': 0.4,
     'density': 70}],
  'boundary_conditions': [
    {'type': 'cuboid', 'point': [1, 1, 0.5], 'size': [0.5, 0.5, 0.28],
     'velocity': [0, 0, 0], 'start_time': 0, 'end_time': 1e3, 'reset': 1},
    {'type': 'particle_impulse', 'force': [-0.18, 0, 0], 'num_dt': 1,
     'start_time': 0}],
  'init_azimuthm': -55.0, 'move_camera': False,
}
_WOLF = {
  'material': 'sand', 'E': 5e7, 'nu': 0.3, 'density': 2000,
  'friction_angle': 30, 'g': [0, 0, -9.8], 'n_grid': 200,
  'substep_dt': 2e-5, 'frame_dt': 4e-2, 'frame_num': 50,
  'boundary_conditions': [
    {'type': 'surface_collider', 'point': [1, 1, 0.48], 'normal': [0, 0, 1],
     'surface': 'sticky', 'friction': 0.0, 'start_time': 0,
     'end_time': 1e3},
    {'type': 'release_particles_sequentially', 'axis': 0, 'num_layers': 50,
     'start_time': 0, 'end_time': 1.5}],
}
_PLANE = {
  'material': 'metal', 'E': 1e5, 'nu': 0.3, 'density': 1000,
  'yield_stress': 1e2, 'g': [0, 0, 0], 'n_grid': 120, 'frame_num': 400,
  'particle_filling': {'n_grid': 128, 'max_partciels_per_cell': 1},
  'boundary_conditions': [
    {'type': 'enforce_particle_velocity_rotation', 'point': [1, 1, 1],
     'normal': [0, 1, 0], 'half_height_and_radius': [0.12, 0.6],
     'rotation_scale': 1.0, 'translation_scale': 0.0, 'start_time': 0,
     'end_time': 0.5}],
}

_ROUND_TRIP_TOL = {np.float32: 2e-6, np.float64: 1e-12}


class ParseTest(parameterized.TestCase):

  @parameterized.named_parameters(
    ('_ficus', _FICUS, 'fixed_corotated', 50, 400),
    ('_wolf', _WOLF, 'drucker_prager', 200, 2000),
    ('_plane', _PLANE, 'von_mises', 120, 100),
  )
  def test_realistic_configs(self, raw, model, n_grid, substeps):
    c = pg.parse_config(raw, warn=False)
    self.assertEqual(c.material, model)
    self.assertEqual(c.n_grid, n_grid)
    self.assertEqual(c.substeps_per_frame, substeps)
    self.assertEqual(c.E, float(raw['E']))
    self.assertEqual(len(c.boundary_conditions),
                     len(raw['boundary_conditions']))
    # Static: hashable, equal configs hash equal.
    self.assertEqual(hash(c), hash(pg.parse_config(raw, warn=False)))

  def test_defaults_match_decode_param(self):
    c = pg.parse_config({}, warn=False)
    self.assertEqual(
      (c.material, c.E, c.nu, c.density, c.g, c.grid_lim, c.n_grid,
       c.substep_dt, c.frame_dt, c.frame_num, c.opacity_threshold),
      ('fixed_corotated', 1e5, 0.4, 200.0, (0.0, 0.0, -9.8), 2.0, 50, 1e-4,
       1e-2, 100, 0.02))

  def test_scalar_gravity(self):
    self.assertEqual(pg.parse_config({'g': 5}, warn=False).g,
                     (0.0, 0.0, -5.0))

  def test_field_values(self):
    c = pg.parse_config(_FICUS, warn=False)
    cub, imp = c.boundary_conditions
    self.assertEqual(cub.type, 'cuboid')
    self.assertEqual(cub.get('size'), (0.5, 0.5, 0.28))
    self.assertEqual(imp.get('num_dt'), 1)
    self.assertEqual(c.additional_material_params[0].density, 70.0)
    self.assertEqual(c.camera.init_azimuth, -55.0)
    w = pg.parse_config(_WOLF, warn=False)
    self.assertEqual(w.friction_angle, 30.0)
    self.assertEqual(w.boundary_conditions[0].get('surface'), 'sticky')

  @parameterized.parameters(
    ('jelly', 'fixed_corotated'), ('metal', 'von_mises'),
    ('sand', 'drucker_prager'), ('foam', 'foam'), ('snow', 'snow'),
    ('plasticine', 'plasticine'), ('neo-hookean', 'neo_hookean'),
    (0, 'fixed_corotated'), (1, 'von_mises'), (2, 'drucker_prager'),
    (3, 'foam'), (4, 'snow'), (5, 'plasticine'), (6, 'neo_hookean'),
    ('stvk', 'stvk'), ('Newtonian', 'newtonian'), ('bingham', 'bingham'),
  )
  def test_material_names(self, name, model):
    self.assertEqual(pg.material_name(name), model)

  def test_examples_load(self):
    names = sorted(f for f in os.listdir(_EXAMPLES) if f.endswith('.json'))
    self.assertGreaterEqual(len(names), 3)
    for name in names:
      c = pg.load_config(os.path.join(_EXAMPLES, name), warn=False)
      self.assertIn(c.material, pg.CANONICAL_MODELS)

  def test_warns_about_unhonoured_fields(self):
    with self.assertLogs(level='WARNING') as logs:
      pg.parse_config(_PLANE)
    self.assertTrue(any('particle_filling' in m for m in logs.output))
    # A misspelt field is ignored with the field it was likely meant as.
    with self.assertLogs(level='WARNING') as logs:
      pg.parse_config({**_PLANE, 'substep_dtt': 1e-4})
    self.assertIn("did you mean 'substep_dt' for 'substep_dtt'?",
                  ' '.join(logs.output))
    # Physics3D's viscoelastic keys are fields (not a misspelt
    # plastic_viscosity).
    c = pg.parse_config({**_PLANE, 'mu_N': 2, 'lam_N': 1, 'viscosity': 10},
                        warn=False)
    self.assertEqual((c.mu_N, c.lam_N, c.viscosity), (2.0, 1.0, 10.0))

  def test_a_blow_up_names_the_json_fields(self):
    # The solver's fix spoke of mpm.choose_substeps and dt.
    from physsplat_jax.mpm import base
    from physsplat_jax.physgaussian import driver
    c = pg.parse_config({**_PLANE, 'boundary_conditions': [
      {'type': 'particle_impulse', 'force': [0, 0, 1e7], 'num_dt': 1,
       'start_time': 0.0}]}, source='kick.json')
    from physsplat_jax.mpm import solver
    sc = types.SimpleNamespace(dt=1e-4)
    stats = dict(nonfinite=5, wall=0, too_fast=0, max_F=1.0, min_J=1.0,
                 max_J=1.0, max_speed=0.0)
    with self.assertRaises(base.SimulationError) as cm:
      solver.check_state(sc, stats, 3, 0.1)
    got = driver._json_fix(cm.exception, c, sc)
    self.assertEqual((got.frame, got.reason), (3, 'nan'))
    self.assertEqual(
      str(got), 'kick.json: frame 3 (t = 0.1 s): 5 particles have NaN/inf '
      'positions, velocities or F: the simulation blew up, most likely '
      'because the time step is too large for the stiffest material. Lower '
      'substep_dt in the JSON (now 0.0001 s; --auto_substeps picks one '
      'stable at the start, not for speeds gained later), lower E, the '
      'particle_impulse speeds or forces, or raise grid_lim if it was thrown '
      'out of the grid.')


class ErrorTest(parameterized.TestCase):

  @parameterized.named_parameters(
    ('_unknown_material', {'material': 'rubberish'}, 'rubberish'),
    ('_unknown_id', {'material': 9}, 'unknown material id'),
    ('_E_string', {'E': '2e6'}, "'E'"),
    ('_bool_E', {'E': True}, "'E'"),
    ('_n_grid_float', {'n_grid': 50.5}, "'n_grid'"),
    # The JSON check took 4, then mpm.GridSpec refused it naming neither.
    ('_n_grid_small', {'n_grid': 4}, r"'n_grid' = 4 is too small.*>= 8"),
    ('_nu_range', {'nu': 0.6}, "'nu'"),
    # nu = 0.5 (incompressible: lambda infinite) passed the check before.
    ('_nu_half', {'nu': 0.5}, r"'nu' = 0\.5 is outside \[0, 0\.5\)"),
    ('_box_nu_half', {'additional_material_params': [
      {'point': [1, 1, 1], 'size': [0.1, 0.1, 0.1], 'nu': 0.5}]},
     r"additional_material_params\[0\]\.nu' = 0\.5 is outside \[0, 0\.5\)"),
    ('_negative_density', {'density': -1}, "'density'"),
    ('_g_len', {'g': [0, -9.8]}, "'g'"),
    ('_bc_type', {'boundary_conditions': [{'type': 'wall'}]}, 'wall'),
    ('_bc_missing', {'boundary_conditions': [{'type': 'cuboid'}]}, 'point'),
    ('_bc_vec', {'boundary_conditions': [
      {'type': 'particle_impulse', 'force': 1.0, 'num_dt': 1}]}, 'force'),
    ('_surface', {'boundary_conditions': [
      {'type': 'surface_collider', 'point': [1, 1, 0], 'normal': [0, 0, 1],
       'surface': 'glue', 'friction': 0.1}]}, 'glue'),
    ('_rotation', {'rotation_degree': [90], 'rotation_axis': []},
     'rotation_axis'),
    ('_axis', {'rotation_degree': [90], 'rotation_axis': [3]},
     'rotation_axis'),
    ('_sim_area', {'sim_area': [0, 1, 0, 1, 1, 0]}, 'sim_area'),
    ('_box', {'additional_material_params': [{'point': [1, 1, 1]}]},
     'size'),
    ('_dt', {'substep_dt': 0.1, 'frame_dt': 0.01}, 'substep_dt'),
    # Accepted before: a box of negative size, a window that ends before
    # it starts, a zero normal (that one failed later, naming no file).
    ('_bc_size', {'boundary_conditions': [
      {'type': 'cuboid', 'point': [1, 1, 1], 'size': [-0.1, 0.1, 0.1],
       'velocity': [0, 0, 0]}]}, r"\.size' = \[-0\.1, 0\.1, 0\.1\]: give "
     'half-extents > 0'),
    ('_bc_window', {'boundary_conditions': [
      {'type': 'cuboid', 'point': [1, 1, 1], 'size': [0.1, 0.1, 0.1],
       'velocity': [0, 0, 0], 'start_time': 1.0, 'end_time': 0.5}]},
     'end_time 0.5 is before start_time 1.0'),
    ('_bc_normal', {'boundary_conditions': [
      {'type': 'surface_collider', 'point': [1, 1, 0], 'normal': [0, 0, 0],
       'surface': 'sticky', 'friction': 0.1}]}, r"\.normal' = .*non-zero"),
    # Accepted before and simulated with a wrong or no effect.
    ('_friction_angle', {'material': 'sand', 'friction_angle': 120},
     r"^x\.json: field 'friction_angle' = 120: use an angle in \[0, 90\)"),
    ('_yield_stress', {'material': 'metal', 'yield_stress': -1},
     r"'yield_stress' = -1: use a stress >= 0"),
    ('_xi', {'material': 'snow', 'xi': 1e3}, r"'xi' = 1000: use"),
    ('_damping', {'grid_v_damping_scale': -1},
     r"'grid_v_damping_scale' = -1: use a factor in \(0, 1\)"),
    ('_damping_zero', {'grid_v_damping_scale': 0},
     r"'grid_v_damping_scale' = 0: use"),
    ('_friction', {'boundary_conditions': [
      {'type': 'surface_collider', 'point': [1, 1, 0], 'normal': [0, 0, 1],
       'surface': 'slip', 'friction': -1}]},
     r"boundary_conditions\[0\]\.friction' = -1: use a Coulomb coefficient "
     '>= 0'),
    ('_release_axis', {'boundary_conditions': [
      {'type': 'release_particles_sequentially', 'axis': 5,
       'start_position': 0.5, 'end_position': 1.5}]},
     r"\.axis' = 5: use 0 \(x\), 1 \(y\) or 2 \(z\)"),
    ('_num_dt_zero', {'boundary_conditions': [
      {'type': 'particle_impulse', 'force': [1, 0, 0], 'num_dt': 0}]},
     r"\.num_dt' = 0: use a number of substeps >= 1"),
    ('_num_dt_negative', {'boundary_conditions': [
      {'type': 'particle_impulse', 'force': [1, 0, 0], 'num_dt': -5}]},
     r"\.num_dt' = -5: use"),
    ('_box_size', {'additional_material_params': [
      {'point': [1, 1, 1], 'size': [-0.1, 0.1, 0.1], 'E': 1e5}]},
     r"additional_material_params\[0\]\.size' = \[-0\.1, 0\.1, 0\.1\]: "
     'give half-extents > 0'),
    # DreamPhysics / Physics3D / PhysFlow units (E / 1e7) read as Pa: a
    # jelly of 0.1 Pa that cannot hold its shape.
    ('_E_scaled_units', {'E': 0.1},
     r"^x\.json: field 'E' = 0\.1 Pa is below 1 Pa: .* PhysFlow config "
     r'gives E / 1e7 .* here E = 1e\+06\.$'),
    ('_box_E_scaled_units', {'additional_material_params': [
      {'point': [1, 1, 1], 'size': [0.1, 0.1, 0.1], 'E': 0.01}]},
     r"additional_material_params\[0\]\.E' = 0\.01 Pa is below 1 Pa: .* "
     r'here E = 1e\+05\.$'),
    # A typo fell back to the default region (all particles).
    ('_bc_typo', {'boundary_conditions': [
      {'type': 'particle_impulse', 'force': [1, 0, 0], 'num_dt': 1,
       'pointt': [1, 1, 1]}]},
     r"boundary_conditions\[0\]' \(particle_impulse\): unknown key "
     r"'pointt' \(did you mean 'point'\?\); particle_impulse takes "
     r"\['force', 'num_dt', 'point', 'size', 'start_time', 'type'\]"),
    ('_bc_key_of_other_type', {'boundary_conditions': [
      {'type': 'cuboid', 'point': [1, 1, 1], 'size': [0.1, 0.1, 0.1],
       'velocity': [0, 0, 0], 'friction': 0.0}]},
     r"\(cuboid\): unknown key 'friction'"),
  )
  def test_bad_field(self, raw, needle):
    with self.assertRaisesRegex(pg.ConfigError, needle):
      pg.parse_config(raw, source='x.json', warn=False)

  def test_replace_checks_ranges(self):
    c = pg.parse_config(_WOLF, warn=False)
    for kw, needle in (({'friction_angle': 90.0}, "'friction_angle' = 90"),
                       ({'grid_v_damping_scale': -0.5},
                        "'grid_v_damping_scale'")):
      with self.subTest(**kw), self.assertRaisesRegex(pg.ConfigError,
                                                      needle):
        c.replace(**kw)

  def test_physgaussian_bc_keys_accepted(self):
    # Every key PhysGaussian's set_boundary_conditions reads, per type
    # (its configs: ficus, pillow2sofa, plane, tear_bread, vasedeck, wolf).
    w = {'start_time': 0.0, 'end_time': 1.5}
    box = {'point': [1, 1, 1], 'size': [0.2, 0.2, 0.2],
           'velocity': [0, 0, 0], **w}
    bcs = [
      {'type': 'bounding_box'},
      {'type': 'cuboid', 'reset': 1, **box},
      {'type': 'enforce_particle_translation', **box},
      {'type': 'particle_impulse', 'force': [1, 0, 0], 'num_dt': 2,
       'start_time': 0.0, 'point': [1, 1, 1], 'size': [1, 1, 1]},
      {'type': 'enforce_particle_velocity_rotation', 'point': [1, 1, 1],
       'normal': [0, 1, 0], 'half_height_and_radius': [0.1, 0.5],
       'rotation_scale': 1.0, 'translation_scale': 0.0, **w},
      {'type': 'surface_collider', 'point': [1, 1, 0.5], 'normal': [0, 0, 1],
       'surface': 'slip', 'friction': 0.4, **w},
      {'type': 'release_particles_sequentially', 'normal': [1, 0, 0],
       'start_position': 1.5, 'end_position': 0.5, 'num_layers': 50, **w},
    ]
    c = pg.parse_config({'boundary_conditions': bcs}, warn=False)
    self.assertLen(c.boundary_conditions, len(bcs))
    # add_bounding_box's window: accepted, ignored (as in PhysGaussian),
    # and said so.
    with self.assertLogs(level='WARNING') as logs:
      pg.parse_config({'boundary_conditions': [
        {'type': 'bounding_box', 'start_time': 0, 'end_time': 1}]})
    self.assertTrue(any('ignored' in m for m in logs.output))

  def test_incompressible_nu_names_file_and_field(self):
    with tempfile.TemporaryDirectory() as d:
      path = os.path.join(d, 'half.json')
      for raw, field in (({'nu': 0.5}, "'nu'"),
                         ({'additional_material_params': [
                           {'point': [1, 1, 1], 'size': [0.1, 0.1, 0.1],
                            'nu': 0.5}]},
                          "'additional_material_params[0].nu'")):
        with open(path, 'w') as f:
          json.dump(raw, f)
        want = (f'{re.escape(path)}: field {re.escape(field)} = 0.5 is '
                r'outside \[0, 0\.5\); use a Poisson ratio')
        with self.subTest(field), self.assertRaisesRegex(pg.ConfigError,
                                                         want):
          pg.load_config(path, warn=False)

  def test_type_error_names_value_and_type(self):
    with self.assertRaises(pg.ConfigError) as cm:
      pg.parse_config({'density': 'heavy'}, source='x.json', warn=False)
    msg = str(cm.exception)
    for part in ('x.json', "'density'", "'heavy'", 'str', 'a number'):
      self.assertIn(part, msg)

  def test_missing_file_and_bad_json(self):
    with self.assertRaisesRegex(pg.ConfigError, 'does not exist'):
      pg.load_config('/nonexistent/cfg.json')
    # A library call names no command-line flag (it said --config=, while
    # experiments.simulate takes the file as --physgaussian).
    with self.assertRaises(pg.ConfigError) as cm:
      pg.load_config('/nonexistent/cfg.json')
    self.assertNotIn('--config', str(cm.exception))
    with tempfile.TemporaryDirectory() as d:
      path = os.path.join(d, 'bad.json')
      with open(path, 'w') as f:
        f.write('{"E": 1e5,}')
      with self.assertRaisesRegex(pg.ConfigError, 'invalid JSON'):
        pg.load_config(path)
      with open(path, 'w') as f:
        json.dump([1, 2], f)
      with self.assertRaisesRegex(pg.ConfigError, 'JSON object'):
        pg.load_config(path)

  def test_directory_and_non_utf8_file(self):
    with tempfile.TemporaryDirectory() as d:
      # A directory said "does not exist".
      with open(os.path.join(d, 'wolf.json'), 'w') as f:
        json.dump(_WOLF, f)
      with self.assertRaisesRegex(
          pg.ConfigError, f"{re.escape(repr(d))} is a directory \\(it holds "
          r'wolf\.json\); pass the path of the \.json config file'):
        pg.load_config(d)
      # Latin-1 text raised a UnicodeDecodeError naming no file.
      path = os.path.join(d, 'latin1.json')
      with open(path, 'wb') as f:
        f.write(b'{"material": "jelly",\n "note": "caf\xe9"}')
      with self.assertRaisesRegex(
          pg.ConfigError, f'{re.escape(path)}: not UTF-8 text '
          r'\(byte 0xe9 on line 2\); save the config as UTF-8'):
        pg.load_config(path)
      # A UTF-8 byte-order mark is fine.
      with open(path, 'wb') as f:
        f.write(b'\xef\xbb\xbf' + json.dumps(_WOLF).encode())
      self.assertEqual(pg.load_config(path, warn=False).friction_angle, 30.0)


class TransformTest(parameterized.TestCase):

  def _points(self, dtype):
    rng = np.random.default_rng(0)
    return (rng.normal(size=(300, 3)) * [3.0, 1.0, 0.5] + [10, -2, 4]
            ).astype(dtype)

  @parameterized.parameters(np.float32, np.float64)
  def test_round_trip(self, dtype):
    with jax.enable_x64(dtype == np.float64):
      c = pg.parse_config({'rotation_degree': [30.0, -70.0],
                           'rotation_axis': [0, 2], 'scale': 0.8}, warn=False)
      x = self._points(dtype)
      t = pg.make_norm_transform(c, x, dtype=dtype)
      xn = pg.normalise_positions(t, jnp.asarray(x))
      back = pg.denormalise_positions(t, xn)
      scale = np.abs(x).max()
      np.testing.assert_allclose(np.asarray(back), x,
                                 atol=_ROUND_TRIP_TOL[dtype] * scale * 4)
      v = jnp.asarray(x[:5])
      np.testing.assert_allclose(
        np.asarray(pg.denormalise_velocity(t, pg.normalise_velocity(t, v))),
        x[:5], atol=_ROUND_TRIP_TOL[dtype] * scale * 4)

  def test_normalised_box_is_centred_unit_cube(self):
    with jax.enable_x64(True):
      c = pg.parse_config({'rotation_degree': [45.0], 'rotation_axis': [1]},
                          warn=False)
      x = self._points(np.float64)
      t = pg.make_norm_transform(c, x, dtype=jnp.float64)
      xn = np.asarray(pg.normalise_positions(t, jnp.asarray(x)))
      lo, hi = xn.min(0), xn.max(0)
      np.testing.assert_allclose(0.5 * (lo + hi), [1, 1, 1], atol=1e-12)
      self.assertAlmostEqual(float(np.max(hi - lo)), 1.0, places=12)

  def test_scale_leaving_the_grid_is_named(self):
    # (This message used to be a NameError from inside the transform.)
    c = pg.parse_config({'scale': 50.0}, warn=False)
    with self.assertRaisesRegex(pg.ConfigError, r"field 'scale' = 50\.0: "
                                'the object cube .* leaves the grid'):
      pg.make_norm_transform(c, self._points(np.float32))

  def test_rotation_matrix(self):
    c = pg.parse_config({'rotation_degree': [90.0], 'rotation_axis': [2]},
                        warn=False)
    R = pg.rotation_matrix(c)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)

  def test_select_particles(self):
    c = pg.parse_config({'sim_area': [0, 1, 0, 1, 0, 1],
                         'opacity_threshold': 0.5}, warn=False)
    x = np.array([[0.5, 0.5, 0.5], [2, 0.5, 0.5], [0.2, 0.2, 0.2]])
    ids = pg.select_particles(c, x, np.array([0.9, 0.9, 0.1]))
    np.testing.assert_array_equal(ids, [0])
    with self.assertRaisesRegex(pg.ConfigError, 'no Gaussians left'):
      pg.select_particles(c, x[1:2])

  def test_material_fields_and_gradient(self):
    c = pg.parse_config(_FICUS, warn=False)
    xn = jnp.array([[1.0, 1.0, 1.5], [1.0, 1.0, 0.7]])

    def total_mass_like(E0):
      params = pg.material_params(c).replace(E=E0)
      E, nu, rho = pg.material_fields(c, xn, params)
      return jnp.sum(E * rho)

    E, nu, rho = pg.material_fields(c, xn)
    np.testing.assert_allclose(np.asarray(rho), [70.0, 200.0])
    np.testing.assert_allclose(np.asarray(E), [2e6, 2e6])
    # Only the particle outside the box depends on the base E.
    self.assertAlmostEqual(float(jax.grad(total_mass_like)(2e6)), 200.0)

  def test_box_without_density_takes_the_base_density(self):
    # decode_param fills a box's missing density with the base density,
    # which overwrites an earlier box's (it was the earlier box's 70).
    boxes = [
      {'point': [1, 1, 1], 'size': [0.5, 0.5, 0.5], 'E': 2e6, 'nu': 0.3,
       'density': 70},
      {'point': [1, 1, 1], 'size': [0.2, 0.2, 0.2], 'E': 5e6, 'nu': 0.3}]
    c = pg.parse_config({'density': 200, 'E': 1e5,
                         'additional_material_params': boxes}, warn=False)
    E, _, rho = pg.material_fields(c, jnp.array([[1.0, 1, 1], [1.3, 1, 1]]))
    np.testing.assert_allclose(np.asarray(rho), [200.0, 70.0])
    np.testing.assert_allclose(np.asarray(E), [5e6, 2e6])

  def test_impulse_defaults_as_set_boundary_conditions(self):
    # PhysGaussian reads num_dt (default 1) and start_time (default 0) as
    # optional; a config without them was refused.
    c = pg.parse_config({'boundary_conditions': [
      {'type': 'particle_impulse', 'force': [1, 0, 0]}]}, warn=False)
    imp, = pg.convert_boundary_conditions(c)
    self.assertEqual((imp.num_dt, imp.start_time), (1, 0.0))
    self.assertEqual((imp.point, imp.size), ((1.0,) * 3, (1.0,) * 3))

  def test_cfl_substep_scales_with_wave_speed(self):
    a = pg.parse_config({'E': 1e6, 'density': 100}, warn=False)
    b = pg.parse_config({'E': 4e6, 'density': 100}, warn=False)
    self.assertAlmostEqual(pg.cfl_substep(a) / pg.cfl_substep(b), 2.0)


if __name__ == '__main__':
  absltest.main()
