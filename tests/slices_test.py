"""Tests for physsplat_jax.render.slices (space-time slices) and their PNG."""

import os
import shutil
import tempfile

import numpy as np
from absl.testing import absltest

from physsplat_jax.io import video
from physsplat_jax.render import slices


def _moving_edge(T=12, H=20, W=40, x0=5, v=2):
  """White for columns j < x0 + v t (a vertical edge moving right)."""
  j = np.arange(W)
  frames = np.zeros((T, H, W, 3), np.float32)
  for t in range(T):
    frames[t, :, j < x0 + v * t] = 1.0
  return frames


class SliceTest(absltest.TestCase):

  def test_moving_edge_gives_the_expected_diagonal(self):
    T, x0, v = 12, 5, 2
    frames = _moving_edge(T, x0=x0, v=v)
    s = np.asarray(slices.space_time_slice(frames, row=7))
    self.assertEqual(s.shape, (T, 40, 3))
    # Row t of the slice is white up to the edge at x0 + v t: the boundary
    # is the line x = x0 + v t.
    edge = np.argmin(s[:, :, 0] > 0.5, axis=1)
    np.testing.assert_array_equal(edge, x0 + v * np.arange(T))
    # time_axis=1 is the transpose.
    s1 = np.asarray(slices.space_time_slice(frames, row=7, time_axis=1))
    np.testing.assert_array_equal(s1, np.swapaxes(s, 0, 1))
    # A column is constant over space and switches on once the edge passes.
    c = np.asarray(slices.space_time_slice(frames, column=10))
    self.assertEqual(c.shape, (T, 20, 3))
    on = c[:, 0, 0] > 0.5
    np.testing.assert_array_equal(on, x0 + v * np.arange(T) > 10)
    np.testing.assert_array_equal(c, np.broadcast_to(c[:, :1], c.shape))

  def test_segments(self):
    frames = _moving_edge()
    # A horizontal segment between integer points is the row, exactly.
    seg = np.asarray(slices.space_time_slice(frames, start=(0, 7),
                                             end=(39, 7)))
    np.testing.assert_allclose(seg, frames[:, 7], atol=1e-6)
    # A diagonal through a linear ramp samples the ramp linearly.
    H, W = 30, 50
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    ramp = np.stack([0.01 * xx + 0.02 * yy] * 3, -1)[None]
    pts = slices.line_points((3, 4), (40, 25), num_samples=17)
    d = np.asarray(slices.space_time_slice(ramp, start=(3, 4), end=(40, 25),
                                           num_samples=17))
    want = 0.01 * pts[:, 0] + 0.02 * pts[:, 1]
    np.testing.assert_allclose(d[0, :, 0], want, atol=1e-5)
    self.assertEqual(len(slices.line_points((0, 0), (3, 4))), 6)

  def test_errors_and_draw_line(self):
    frames = _moving_edge()
    with self.assertRaisesRegex(ValueError, 'exactly one'):
      slices.space_time_slice(frames, row=1, column=2)
    with self.assertRaisesRegex(ValueError, 'row 99'):
      slices.space_time_slice(frames, row=99)
    with self.assertRaisesRegex(ValueError, r'\(T, H, W, C\)'):
      slices.space_time_slice(frames[0], row=1)
    img = np.asarray(slices.draw_line(frames[0], start=(0, 0), end=(9, 9),
                                      color=(1.0, 0.0, 0.0)))
    np.testing.assert_array_equal(img[5, 5], [1.0, 0.0, 0.0])

  def test_png(self):
    d = tempfile.mkdtemp()
    self.addCleanup(shutil.rmtree, d, ignore_errors=True)
    frames = _moving_edge()
    path = os.path.join(d, 'slice.png')
    img = video.save_space_time_slice(
      path, slices.space_time_slice(frames, row=7), time_scale=3)
    back = video.load_png(path)
    self.assertEqual(back.shape, (36, 40, 3))
    np.testing.assert_array_equal(back, img)
    want = np.round(frames[:, 7] * 255).astype(np.uint8)
    np.testing.assert_array_equal(back[::3], want)


if __name__ == '__main__':
  absltest.main()
