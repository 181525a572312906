"""Smoke test of experiments/ablate_sampling.py (tiny scene, marked slow)."""

import numpy as np
import pytest
from absl.testing import absltest

from experiments import ablate_sampling


@pytest.mark.slow
class AblateSamplingTest(absltest.TestCase):

  def test_tiny_run(self):
    rows = ablate_sampling.run([150], num=400, grid_res=16, num_frames=2,
                               methods=('pgas', 'uniform', 'kmeans',
                                        'pgas-cvt'),
                               fill_res=12, log=lambda s: None)
    self.assertEqual(rows[0]['method'], 'all (reference)')
    by = {r['method']: r for r in rows[1:]}
    self.assertEqual(set(by), {'pgas', 'uniform', 'kmeans', 'pgas-cvt'})
    self.assertEqual(by['pgas-cvt']['n'], 150)  # exactly the budget
    for r in by.values():
      self.assertLessEqual(r['n'], 150)
      # Driven Gaussians follow the reference to within the sphere radius
      # over two frames (they start at the reference positions exactly).
      self.assertTrue(np.isfinite(r['err_all']))
      self.assertLess(r['err_all'], 0.5)


if __name__ == '__main__':
  absltest.main()
