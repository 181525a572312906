"""Tests for physsplat_jax.io.video: MP4 round trip, GIF fallback, PNG frames,
bad-frame errors."""

import os
import shutil
import tempfile

import jax.numpy as jnp
import numpy as np
from absl.testing import absltest
from absl.testing import parameterized

from physsplat_jax.io import video

# H.264 at quality 8 on smooth content: mean abs error in 8-bit levels.
_MP4_MEAN_ERR = 3.0
_MP4_MAX_ERR = 40


def _smooth_frames(T=6, H=40, W=56):
  """Moving colour gradients (easy for the encoder, unlike noise)."""
  t = np.arange(T)[:, None, None]
  i = np.arange(H)[None, :, None]
  j = np.arange(W)[None, None, :]
  r = 0.5 + 0.4 * np.sin(0.1 * j + 0.3 * t) * np.ones_like(i)
  g = 0.5 + 0.4 * np.cos(0.08 * i - 0.2 * t) * np.ones_like(j)
  b = np.broadcast_to((i + j) / (H + W), r.shape)
  return np.stack(np.broadcast_arrays(r, g, b), -1).astype(np.float32)


class Mp4Test(parameterized.TestCase):

  def setUp(self):
    super().setUp()
    self.dir = tempfile.mkdtemp()
    self.addCleanup(shutil.rmtree, self.dir, ignore_errors=True)

  @parameterized.named_parameters(
    ('_even', 40, 56, 40, 56),
    ('_odd_is_padded', 33, 47, 34, 48),
  )
  def test_round_trip_shape_count_and_content(self, H, W, H2, W2):
    frames = _smooth_frames(7, H, W)
    path = video.write_video(os.path.join(self.dir, 'a.mp4'), frames, fps=12)
    self.assertTrue(path.endswith('.mp4'))
    back = video.read_video(path)
    self.assertEqual(back.shape, (7, H2, W2, 3))
    err = np.abs(back[:, :H, :W].astype(np.float64)
                 - np.round(frames * 255.0))
    self.assertLess(err.mean(), _MP4_MEAN_ERR)
    self.assertLess(err.max(), _MP4_MAX_ERR)
    # The padding repeats the last row/column (no rescaling).
    if H2 > H:
      np.testing.assert_allclose(back[:, H].astype(float),
                                 back[:, H - 1].astype(float), atol=12)

  def test_streaming_writer_jax_and_uint8_frames(self):
    frames = _smooth_frames(5)
    path = os.path.join(self.dir, 'sub', 'b.mp4')
    with video.VideoWriter(path, fps=25) as w:
      for k, f in enumerate(frames):
        w.append(jnp.asarray(f) if k % 2 else (f * 255).round().astype(
          np.uint8))
      self.assertEqual(w.format, 'mp4')
    self.assertEqual(w.num_frames, 5)
    self.assertEqual(w.size, (56, 40))
    self.assertEqual(video.read_video(path).shape[0], 5)

  def test_bad_frames_raise_clear_errors(self):
    path = os.path.join(self.dir, 'c.mp4')
    with video.VideoWriter(path) as w:
      with self.assertRaisesRegex(video.VideoError, r'shape \(8, 8\)'):
        w.append(np.zeros((8, 8)))
      with self.assertRaisesRegex(video.VideoError, 'RGB'):
        w.append(np.zeros((8, 8, 4)))
      bad = np.zeros((8, 8, 3), np.float32)
      bad[2, 5, 1] = np.nan
      with self.assertRaisesRegex(video.VideoError, 'row 2, column 5'):
        w.append(bad)
      with self.assertRaisesRegex(video.VideoError, 'integer dtype'):
        w.append(np.zeros((8, 8, 3), np.int32))
      w.append(np.zeros((8, 8, 3), np.float32))
      with self.assertRaisesRegex(video.VideoError, 'differs from the first'):
        w.append(np.zeros((8, 10, 3), np.float32))
    with self.assertRaisesRegex(video.VideoError, 'after close'):
      w.append(np.zeros((8, 8, 3), np.float32))
    with self.assertRaisesRegex(video.VideoError, 'extension'):
      video.VideoWriter(os.path.join(self.dir, 'x.avi2'))
    with self.assertRaisesRegex(video.VideoError, 'fps'):
      video.VideoWriter(path, fps=0)
    with self.assertRaisesRegex(video.VideoError, r'\(T, H, W, 3\)'):
      video.write_video(path, np.zeros((8, 8, 3)))


class FallbackAndPngTest(absltest.TestCase):

  def test_gif_fallback_without_ffmpeg(self):
    d = tempfile.mkdtemp()
    self.addCleanup(shutil.rmtree, d, ignore_errors=True)
    old = os.environ.get('IMAGEIO_FFMPEG_EXE')
    os.environ['IMAGEIO_FFMPEG_EXE'] = os.path.join(d, 'no-such-ffmpeg')
    try:
      self.assertIsNone(video.find_ffmpeg())
      frames = _smooth_frames(4, 16, 20)
      with self.assertLogs(video.logger, 'WARNING') as logs:
        path = video.write_video(os.path.join(d, 'v.mp4'), frames, fps=10)
      self.assertIn('GIF', logs.output[0])
      with self.assertRaisesRegex(video.VideoError, 'no ffmpeg'):
        video.VideoWriter(os.path.join(d, 'w.mp4'), allow_gif_fallback=False)
    finally:
      if old is None:
        del os.environ['IMAGEIO_FFMPEG_EXE']
      else:
        os.environ['IMAGEIO_FFMPEG_EXE'] = old
    self.assertTrue(path.endswith('v.gif'))
    back = video.read_video(path)
    self.assertEqual(back.shape, (4, 16, 20, 3))
    # GIF quantises to a 256-colour palette.
    self.assertLess(np.abs(back / 255.0 - frames).mean(), 0.03)

  def test_png_frames(self):
    d = tempfile.mkdtemp()
    self.addCleanup(shutil.rmtree, d, ignore_errors=True)
    frames = _smooth_frames(3, 12, 10)
    paths = video.write_png_frames(d, frames)
    self.assertEqual([os.path.basename(p) for p in paths],
                     ['frame_0000.png', 'frame_0001.png', 'frame_0002.png'])
    back = video.load_png(paths[2])
    np.testing.assert_array_equal(back, np.round(frames[2] * 255))
    with self.assertRaisesRegex(video.VideoError, 'integer field'):
      video.PngFrameWriter(d, pattern='frame.png')


if __name__ == '__main__':
  absltest.main()
