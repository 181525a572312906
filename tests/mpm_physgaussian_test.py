"""Tests for running PhysGaussian configs (physsplat_jax.physgaussian)."""

import json
import os
import tempfile

import numpy as np
from absl.testing import absltest

from physsplat_jax import mpm
from physsplat_jax import physgaussian as pg
from physsplat_jax.io import ply
from physsplat_jax import physgaussian as mpm_pg
from physsplat_jax.types import Gaussians

_REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_PLY = os.path.join(_REPO, 'tests', 'data', 'train_1000.ply')
_EXAMPLES = os.path.join(_REPO, 'experiments', 'configs')

_TINY = {
  'material': 'jelly', 'E': 2e4, 'nu': 0.3, 'density': 200,
  'g': [0, 0, -9.8], 'n_grid': 16, 'grid_lim': 2.0, 'substep_dt': 1e-3,
  'frame_dt': 1e-2, 'frame_num': 3, 'scale': 0.8, 'opacity_threshold': 0.1,
  'rotation_degree': [30.0], 'rotation_axis': [0],
  'boundary_conditions': [
    {'type': 'bounding_box'},
    {'type': 'surface_collider', 'point': [1, 1, 0.6], 'normal': [0, 0, 1],
     'surface': 'sticky', 'friction': 0.0, 'start_time': 0,
     'end_time': 1e3}],
}


class ConversionTest(absltest.TestCase):

  def test_grid_volumes_match_occupancy(self):
    x = np.array([[0.05, 0.05, 0.05], [0.06, 0.07, 0.05], [0.5, 0.5, 0.5]])
    vol = mpm_pg.grid_volumes(x, n_grid=10, grid_lim=1.0)
    np.testing.assert_allclose(vol, [5e-4, 5e-4, 1e-3])
    np.testing.assert_allclose(
      mpm_pg.grid_volumes(x, 10, 1.0, uniform=True), np.full(3, 2e-3 / 3))

  def test_example_configs_convert(self):
    for name in sorted(os.listdir(_EXAMPLES)):
      if not name.endswith('.json'):
        continue
      cfg = pg.load_config(os.path.join(_EXAMPLES, name), warn=False)
      sc = mpm_pg.make_sim_config(cfg)
      self.assertEqual(sc.grid.res, cfg.n_grid)
      self.assertEqual(sc.models, (cfg.material,))
      n_bc = sum(bc.type != 'bounding_box' for bc in cfg.boundary_conditions)
      self.assertLen(sc.boundary_conditions, n_bc)
    ficus = pg.load_config(os.path.join(_EXAMPLES, 'ficus.json'), warn=False)
    cub, imp = mpm_pg.make_sim_config(ficus).boundary_conditions
    self.assertIsInstance(cub, mpm.Cuboid)
    self.assertTrue(cub.reset)
    self.assertEqual(imp.force, (-0.18, 0.0, 0.0))
    self.assertEqual(imp.point, (1.0, 1.0, 1.0))  # PhysGaussian default

  def test_impulses_act_before_enforced_velocities(self):
    # PhysGaussian's p2g2p runs the impulses before the velocity modifiers,
    # whatever the list order: the enforced velocity wins (it was 2e-3).
    import jax.numpy as jnp
    from physsplat_jax.mpm import boundary
    raw = dict(_TINY, boundary_conditions=[
      {'type': 'enforce_particle_translation', 'point': [1, 1, 1],
       'size': [1, 1, 1], 'velocity': [0.5, 0, 0], 'start_time': 0,
       'end_time': 1},
      {'type': 'particle_impulse', 'force': [1, 0, 0], 'num_dt': 1,
       'start_time': 0}])
    sc = mpm_pg.make_sim_config(pg.parse_config(raw, warn=False))
    x = jnp.array([[1.0, 1.0, 1.0], [0.5, 0.5, 0.5]])
    data = boundary.particle_bc_data(sc, x)
    z = jnp.zeros(2)
    v, _ = boundary.apply_particle_bcs(
      sc, mpm.make_forces(sc), data, jnp.zeros(()), tuple(x.T), (z,) * 3,
      ((z,) * 3,) * 3, jnp.full(2, 0.5))
    np.testing.assert_allclose(np.asarray(v[0]), [0.5, 0.5], rtol=1e-6)

  def test_release_sequentially_fields(self):
    raw = dict(_TINY, boundary_conditions=[
      {'type': 'release_particles_sequentially', 'normal': [0, 1, 0],
       'start_position': 0.5, 'end_position': 1.5, 'num_layers': 10,
       'start_time': 0.0, 'end_time': 1.5}])
    (bc,) = mpm_pg.make_sim_config(pg.parse_config(raw, warn=False)
                                   ).boundary_conditions
    self.assertEqual((bc.axis, bc.num_layers), (1, 50))
    raw['boundary_conditions'][0].pop('start_position')
    with self.assertRaisesRegex(pg.ConfigError, 'start_position'):
      mpm_pg.make_sim_config(pg.parse_config(raw, warn=False))


class SimulateTest(absltest.TestCase):

  def test_command_line_writes_trajectory(self):
    g = ply.load_ply(_PLY)
    with tempfile.TemporaryDirectory() as d:
      path = os.path.join(d, 'tiny.json')
      with open(path, 'w') as f:
        json.dump(_TINY, f)
      out = mpm_pg.run_config(_PLY, path, os.path.join(d, 'out'))
      data = np.load(out['files']['trajectory'])
      x, ids, t = data['x'], data['ids'], data['t']
    opac = 1 / (1 + np.exp(-np.asarray(g.opacity_logits, np.float64)))
    np.testing.assert_array_equal(ids, np.flatnonzero(opac > 0.1))
    self.assertEqual(x.dtype, np.float32)
    self.assertEqual(x.shape, (4, len(ids), 3))
    np.testing.assert_allclose(t, [0.0, 0.01, 0.02, 0.03])
    # Frame 0 is the input, in the input frame (round trip through the
    # rotated, normalised domain).
    np.testing.assert_allclose(x[0], np.asarray(g.means)[ids], atol=1e-5)
    self.assertTrue(np.all(np.isfinite(x)))
    # Gravity is -z in the *rotated* frame: the motion in the input frame
    # is along R^T (0, 0, -1) = (0, -sin, -cos), R 30 degrees about x.
    d = (x[-1] - x[0]).mean(0)
    c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
    down = np.array([0.0, -s, -c])
    self.assertGreater(d @ down, 0.9 * np.linalg.norm(d))

  def test_unstable_substep_is_reported_or_fixed(self):
    g = ply.load_ply(_PLY)
    cfg = pg.parse_config(dict(_TINY, E=1e8, frame_num=1), warn=False)
    with self.assertRaisesRegex(mpm.SimulationError, 'auto_substeps'):
      mpm_pg.simulate_config(g, cfg)
    x, _, t = mpm_pg.simulate_config(g, cfg.replace(E=2e6),
                                     auto_substeps=True)
    self.assertTrue(np.all(np.isfinite(x)))
    self.assertLen(t, 2)

  def test_physics3d_viscoelastic_branch(self):
    # Physics3D's mu_N, lam_N, viscosity: the Maxwell branch, as (E_N, nu_N)
    # of those Lame parameters; in Pa (Physics3D scales E by 1e7, not
    # these).
    g = ply.load_ply(_PLY)
    cfg = pg.parse_config(dict(_TINY, mu_N=2e5, lam_N=3e5, viscosity=50.0,
                               frame_num=1), warn=False)
    prep = mpm_pg.prepare_config(g, cfg)
    self.assertTrue(prep.sim_config.maxwell)
    mat = prep.materials
    mu, lam = 2e5, 3e5
    np.testing.assert_allclose(mat.maxwell_E[0], mu * (3 * lam + 2 * mu)
                               / (lam + mu), rtol=1e-6)
    np.testing.assert_allclose(mat.maxwell_nu[0], 0.3, rtol=1e-6)
    np.testing.assert_allclose(mat.maxwell_viscosity[0], 50.0)
    x, _, _ = mpm_pg.simulate_config(g, cfg, auto_substeps=True)
    self.assertTrue(np.all(np.isfinite(x)))
    with self.assertRaisesRegex(pg.ConfigError, r'lam_N.*mu_N > 0'):
      pg.parse_config(dict(_TINY, lam_N=1.0), warn=False)
    # Not on sand or a fluid (Physics3D gives it to jelly): named in the
    # config's terms, not as the solver's maxwell_E.
    with self.assertRaisesRegex(pg.ConfigError,
                                r"'mu_N' = 5 on material 'drucker_prager'"):
      pg.parse_config(dict(_TINY, material='sand', mu_N=5.0), warn=False)
    # A viscosity without the branch was an unknown key (warned); it is
    # still said to do nothing.
    with self.assertLogs(level='WARNING') as logs:
      pg.parse_config(dict(_TINY, viscosity=0.5), warn=False)
    self.assertIn('needs "mu_N" > 0', ' '.join(logs.output))
    # Through perception's config materials too.
    from physsplat_jax.perception import choice
    spec = choice.spec_from_physgaussian(cfg)
    np.testing.assert_allclose(spec['maxwell_nu'], 0.3)
    self.assertEqual(spec['maxwell_viscosity'], 50.0)

  def test_particle_filling_adds_simulated_interior(self):
    # A closed spherical shell of Gaussians (radius 1, input units).
    rng = np.random.default_rng(0)
    k = 3000
    u = rng.normal(size=(k, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    g = Gaussians(
      means=u.astype(np.float32),
      log_scales=np.full((k, 3), np.log(0.06), np.float32),
      quats=np.tile(np.float32([1, 0, 0, 0]), (k, 1)),
      opacity_logits=np.full((k,), 4.0, np.float32),
      sh=np.zeros((k, 1, 3), np.float32))
    raw = dict(_TINY, rotation_degree=[], rotation_axis=[],
               particle_filling={'n_grid': 32, 'density_threshold': 0.5})
    prep = mpm_pg.prepare_config(g, pg.parse_config(raw, warn=False))
    self.assertEqual(prep.num_gaussians, k)
    fill = np.asarray(prep.state.x[k:])
    self.assertGreater(len(fill), 50)
    # Fill points lie inside the (normalised) sphere: centre (1,1,1),
    # radius scale / 2 = 0.4.
    r = np.linalg.norm(fill - 1.0, axis=1)
    self.assertLess(r.max(), 0.4)
    # Volumes from occupancy: each particle gets a share of its cell.
    vol = np.asarray(prep.state.vol0)
    dx3 = (2.0 / 16) ** 3
    self.assertTrue(np.all((vol > 0) & (vol <= dx3 * (1 + 1e-6))))


  def test_fill_spacing_spans_the_boundary(self):
    # PhysGaussian's fill grid has particle_filling.n_grid cells over the
    # longest side of "boundary" (0.4 here: spacing 0.0125), not over
    # grid_lim (2: spacing 0.0625, a 5x coarser fill).
    import types
    from unittest import mock
    from physsplat_jax.sampling import filling
    rng = np.random.default_rng(0)
    k = 200
    g = Gaussians(
      means=rng.uniform(-1, 1, (k, 3)).astype(np.float32),
      log_scales=np.full((k, 3), np.log(0.05), np.float32),
      quats=np.tile(np.float32([1, 0, 0, 0]), (k, 1)),
      opacity_logits=np.full((k,), 4.0, np.float32),
      sh=np.zeros((k, 1, 3), np.float32))
    raw = dict(_TINY, rotation_degree=[], rotation_axis=[],
               particle_filling={'n_grid': 32,
                                 'boundary': [0.8, 1.2, 0.8, 1.2, 0.8, 1.2]})
    cfg = pg.parse_config(raw, warn=False)
    seen = {}

    def fake(key, means, *args, config, **kw):
      ext = float(np.max(np.ptp(means, 0)))
      seen['dx'] = ext / (config.grid_res - 2 * config.margin_cells)
      return types.SimpleNamespace(points=np.zeros((0, 3)), overflow=False)

    with mock.patch.object(filling, 'fill_gaussians_host', fake):
      mpm_pg.fill_particles(cfg, g, np.arange(k), None)
    self.assertLess(seen['dx'], 0.0125 * 1.1)


if __name__ == '__main__':
  absltest.main()
