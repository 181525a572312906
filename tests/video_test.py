"""Tests for physsplat_jax.io.video: MP4 round trip, GIF fallback, PNG frames,
bad-frame errors; and io.outputs' background writers."""

import os
import shutil
import tempfile
import threading
import time
from unittest import mock

import jax.numpy as jnp
import numpy as np
from absl.testing import absltest
from absl.testing import parameterized

from physsplat_jax.io import outputs
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


class ToUint8Test(absltest.TestCase):

  def test_rounding_in_every_float_dtype_and_layout(self):
    """round(255 * clip(x, 0, 1)), half to even, computed in float32 (float64
    for float64 frames: the old results, bit for bit; float16 frames no
    longer round in float16); out-of-range values clipped; any memory
    layout in, a C-contiguous frame out; the input untouched."""
    rng = np.random.default_rng(0)
    x = rng.uniform(-0.3, 1.3, (24, 32, 3))
    for dtype in (np.float16, np.float32, np.float64):
      work = np.float64 if dtype == np.float64 else np.float32
      a = x.astype(dtype)
      for frame in (a, np.asfortranarray(a), a[::-1], a.transpose(1, 0, 2)):
        with self.subTest(dtype=np.dtype(dtype).name,
                          c=frame.flags['C_CONTIGUOUS']):
          before = frame.copy()
          got = video.to_uint8(frame)
          self.assertEqual(got.dtype, np.uint8)
          self.assertTrue(got.flags['C_CONTIGUOUS'])
          want = np.round(np.clip(frame.astype(work), 0, 1) * work(255.0))
          np.testing.assert_array_equal(got, want.astype(np.uint8))
          np.testing.assert_array_equal(frame, before)

  def test_non_finite_values_are_named_with_their_pixel(self):
    for bad in (np.nan, np.inf, -np.inf):
      frame = np.full((4, 5, 3), 0.5, np.float32)
      frame[2, 3, 1] = bad
      with self.assertRaisesRegex(video.VideoError,
                                  '1 non-finite values.*row 2, column 3'):
        video.to_uint8(frame, 'frame 7')


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
      # The variable naming no executable is said (it hid the wheel's
      # ffmpeg without a word), then the fallback.
      self.assertIn('no-such-ffmpeg is not an ffmpeg executable',
                    logs.output[0])
      self.assertIn('GIF', logs.output[-1])
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


class BadInputTest(absltest.TestCase):
  """Output that cannot be written is an error naming the file and the
  fix, never a raw OS error or a video that silently is not there."""

  def setUp(self):
    super().setUp()
    self.dir = tempfile.mkdtemp()
    self.addCleanup(shutil.rmtree, self.dir, ignore_errors=True)
    self.file = os.path.join(self.dir, 'file')
    with open(self.file, 'w') as fh:
      fh.write('not a folder')

  def test_ffmpeg_failure_is_raised_not_lost(self):
    frames = np.zeros((3, 8, 8, 3))
    path = os.path.join(self.dir, 'c.mp4')
    with self.assertRaisesRegex(
        video.VideoError, "c.mp4: ffmpeg failed .*Unknown encoder 'nope'.*"
        'nothing was written'):
      video.write_video(path, frames, codec='nope')
    self.assertFalse(os.path.exists(path))
    # Frames larger than the pipe: the error comes at append.
    w = video.VideoWriter(path, codec='nope')
    with self.assertRaisesRegex(video.VideoError, 'Unknown encoder'):
      for _ in range(50):
        w.append(np.zeros((256, 256, 3), np.uint8))
      w.close()
    w.close()  # closed: nothing more to report
    self.assertFalse(os.path.exists(path))
    # A path ffmpeg cannot open (were it not checked first): its reason.
    path = os.path.join(self.dir, 'isdir.mp4')
    os.makedirs(path)
    with mock.patch.object(video, '_check_output',
                           lambda p, create=False: os.fspath(p)):
      with self.assertRaisesRegex(
          video.VideoError, 'isdir.mp4: ffmpeg failed .*Is a directory.*'
          'nothing was written'):
        video.write_video(path, frames)
    self.assertEqual(os.listdir(path), [])
    # Checked up front: the path is a folder.
    with self.assertRaisesRegex(video.VideoError,
                                'isdir.mp4: is a directory; give the video'):
      video.VideoWriter(path)

  def test_float_frames_in_0_255_are_refused(self):
    path = os.path.join(self.dir, 'o.mp4')
    with self.assertRaisesRegex(video.VideoError,
                                r'frame 0: float values up to 200.*/ 255'):
      video.write_video(path, np.full((2, 8, 8, 3), 200.0))
    self.assertFalse(os.path.exists(path))
    with self.assertRaisesRegex(video.VideoError, 'frame / 255'):
      video.save_png(os.path.join(self.dir, 'o.png'),
                     np.full((8, 8, 3), 255.0, np.float32))
    # Overshoot of a render in [0, 1] is still clipped.
    np.testing.assert_array_equal(video.to_uint8(np.full((2, 2, 3), 1.5)),
                                  255)

  def test_output_paths_that_cannot_be_written(self):
    frame = np.zeros((8, 8, 3), np.float32)
    folder = os.path.join(self.dir, 'folder.png')
    os.makedirs(folder)
    with self.assertRaisesRegex(video.VideoError,
                                'folder.png: is a directory; give the'):
      video.save_png(folder, frame)
    gif = os.path.join(self.dir, 'g.gif')
    os.makedirs(gif)
    with self.assertRaisesRegex(video.VideoError, 'g.gif: is a directory'):
      video.write_video(gif, frame[None])
    under = lambda name: os.path.join(self.file, name)
    in_the_way = f"{self.file} is a file, not a folder; choose another"
    for write in (lambda: video.save_png(under('x.png'), frame),
                  lambda: video.write_video(under('x.gif'), frame[None]),
                  lambda: video.write_video(under('x.mp4'), frame[None]),
                  lambda: video.write_png_frames(under('f'), frame[None])):
      with self.assertRaisesRegex(video.VideoError, in_the_way):
        write()
    # The run's writers check their files when made, before any frame.
    with self.assertRaisesRegex(outputs.OutputError, in_the_way):
      outputs.PngOutput(under('frames'))
    with self.assertRaisesRegex(outputs.OutputError, in_the_way):
      outputs.TrajectoryOutput(under('trajectory.npz'), [0])
    os.makedirs(os.path.join(self.dir, 'video.mp4'))
    with self.assertRaisesRegex(outputs.OutputError,
                                'video.mp4: is a directory'):
      outputs.VideoOutput(os.path.join(self.dir, 'video.mp4'), fps=10)
    # A missing folder is made (only when a file is written).
    new = os.path.join(self.dir, 'a', 'b', 'x.png')
    self.assertEqual(outputs.check_output_file(new), new)
    self.assertFalse(os.path.exists(os.path.dirname(new)))
    video.save_png(new, frame)
    self.assertTrue(os.path.isfile(new))


class _Recorder:
  """A writer that records what it got, on which thread, and can fail."""

  def __init__(self, delay=0.0, fail_at=None):
    self.delay, self.fail_at = delay, fail_at
    self.indices, self.threads, self.closed = [], set(), False

  def write(self, frame):
    time.sleep(self.delay)
    if frame.index == self.fail_at:
      raise OSError(f'disk full at frame {frame.index}')
    self.indices.append(frame.index)
    self.threads.add(threading.get_ident())

  def close(self):
    self.closed = True
    return {'rec': str(len(self.indices))}


class BackgroundWritersTest(absltest.TestCase):

  def test_frames_in_order_off_the_loop_thread_and_bounded(self):
    fast, slow = _Recorder(), _Recorder(delay=0.01)
    sink = outputs.BackgroundWriters([fast, slow], max_pending=3)
    for i in range(12):
      sink.write(outputs.Frame(index=i, time=0.1 * i))
      pending = sink._pending  # noqa: SLF001
      self.assertLessEqual(max(len(q) for q in pending), 3)
    self.assertEqual(sink.close(), {'rec': '12'})
    self.assertEqual(fast.indices, list(range(12)))
    self.assertEqual(slow.indices, list(range(12)))
    self.assertTrue(fast.closed and slow.closed)
    self.assertNotIn(threading.get_ident(), fast.threads | slow.threads)

  def test_a_writer_error_is_raised_and_the_others_still_close(self):
    bad, good = _Recorder(fail_at=2), _Recorder()
    sink = outputs.BackgroundWriters([bad, good], max_pending=2)
    with self.assertRaisesRegex(OSError, 'disk full at frame 2'):
      for i in range(50):
        sink.write(outputs.Frame(index=i, time=0.0))
        time.sleep(0.002)
    sink.close()  # raised once, by write; close still closes every writer
    self.assertTrue(bad.closed and good.closed)
    self.assertEqual(bad.indices, [0, 1])
    self.assertEqual(good.indices[:3], [0, 1, 2])

  def test_a_failed_writer_gets_no_queued_frames(self):
    """Frames queued behind the failing one are skipped for that writer
    (they were written when the error was found late), not for others."""
    bad, good = _Recorder(delay=0.02, fail_at=1), _Recorder()
    sink = outputs.BackgroundWriters([bad, good], max_pending=8)
    for i in range(5):  # all queued before frame 1 fails
      sink.write(outputs.Frame(index=i, time=0.0))
    with self.assertRaisesRegex(OSError, 'disk full at frame 1'):
      sink.close()
    self.assertEqual(bad.indices, [0])
    self.assertEqual(good.indices, [0, 1, 2, 3, 4])
    self.assertTrue(bad.closed and good.closed)

  def test_an_error_still_queued_is_raised_by_close(self):
    bad = _Recorder(delay=0.01, fail_at=1)
    sink = outputs.BackgroundWriters([bad], max_pending=8)
    for i in range(3):
      sink.write(outputs.Frame(index=i, time=0.0))
    with self.assertRaisesRegex(OSError, 'disk full at frame 1'):
      sink.close()
    self.assertTrue(bad.closed)

  def test_writers_close_side_by_side_after_their_last_frame(self):
    # Both closes must be running at once to pass the barrier.
    barrier = threading.Barrier(2, timeout=10)

    class Closing(_Recorder):
      def close(self):
        self.seen_at_close = list(self.indices)
        self.close_thread = threading.get_ident()
        barrier.wait()
        return super().close()

    a, b = Closing(delay=0.005), Closing()
    sink = outputs.BackgroundWriters([a, b], max_pending=4)
    for i in range(6):
      sink.write(outputs.Frame(index=i, time=0.0))
    sink.close()
    self.assertEqual(a.seen_at_close, list(range(6)))
    self.assertEqual(b.seen_at_close, list(range(6)))
    self.assertNotEqual(a.close_thread, b.close_thread)
    self.assertNotIn(threading.get_ident(), (a.close_thread, b.close_thread))

  def test_png_output_through_the_background_writer(self):
    d = tempfile.mkdtemp()
    self.addCleanup(shutil.rmtree, d, ignore_errors=True)
    # A longer earlier run's frames go (they used to stay behind this
    # run's); the user's other files stay.
    for name in ('frame_0002.png', 'frame_0007.png', 'notes.txt'):
      with open(os.path.join(d, name), 'w') as fh:
        fh.write('old')
    frames = _smooth_frames(4, 12, 10)
    sink = outputs.BackgroundWriters([outputs.PngOutput(d)])
    for i, f in enumerate(frames):
      sink.write(outputs.Frame(index=i, time=0.0, image=f))
    self.assertEqual(sink.close(), {'frames': d})
    self.assertEqual(sorted(os.listdir(d)),
                     [f'frame_{i:04d}.png' for i in range(4)] + ['notes.txt'])
    back = video.load_png(os.path.join(d, 'frame_0003.png'))
    np.testing.assert_array_equal(back, np.round(frames[3] * 255))


if __name__ == '__main__':
  absltest.main()
