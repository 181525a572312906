"""experiments/ablate_sampling.py: smoke test (tiny scene, marked slow) and
the summary over seeds."""

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


class SummarizeTest(absltest.TestCase):

  def test_methods_are_checked_before_the_reference_run(self):
    from absl import app  # noqa: PLC0415
    ablate_sampling.check_methods(
      ['pgas', 'pgas-scaled', 'pgas+lloyd', 'uniform', 'kmeans', 'pgas-cvt',
       'pgas-cvt:density_power=0.5/weights=volume'])
    for bad in ('bogus', 'pgas+more', 'uniform:x=1', 'pgas-cvt:nosuch=1',
                'pgas-cvt:density_power=x'):
      with self.subTest(bad), self.assertRaisesRegex(app.UsageError,
                                                     '--methods'):
        ablate_sampling.check_methods([bad])

  def test_ratio_interval_and_wins_over_seeds(self):
    ratios = [0.5, 0.8, 1.25, 0.4]
    rows = []
    for seed, r in enumerate(ratios):
      rows += [dict(scene='s', seed=seed, budget=500, method='kmeans',
                    err_all=2e-3),
               dict(scene='s', seed=seed, budget=500, method='pgas-cvt',
                    err_all=2e-3 * r)]
    rows.append(dict(scene='s', seed=9, budget=500, method='pgas-cvt',
                     err_all=1.0))  # no K-means row for seed 9: not paired
    (out,) = ablate_sampling.summarize(rows, log=None)
    self.assertEqual(out['seeds'], 4)
    self.assertEqual(out['wins'], 3)
    self.assertAlmostEqual(out['ratio'], float(np.prod(ratios)) ** 0.25)
    self.assertLess(out['lo'], out['ratio'])
    self.assertLess(out['ratio'], out['hi'])
    self.assertGreater(out['hi'], 1.0)  # four noisy seeds decide nothing


if __name__ == '__main__':
  absltest.main()
