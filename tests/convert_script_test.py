"""experiments.convert: scene files between PLY, .splat and .spz."""

import os
import subprocess
import sys
import tempfile

import jax
import numpy as np
from absl.testing import absltest

from physsplat_jax import test_util
from physsplat_jax.io import ply
from physsplat_jax.io import spz
from physsplat_jax.io.splat import load_splat

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_DONUT = os.path.join(_ROOT, 'physsplat_jax', 'data', 'scenes', 'donut.ply')


def _convert(*args):
  proc = subprocess.run([sys.executable, '-m', 'experiments.convert', *args],
                        capture_output=True, text=True, check=False,
                        timeout=120, cwd=_ROOT)
  return proc.returncode, proc.stdout, proc.stderr


class ConvertTest(absltest.TestCase):

  def setUp(self):
    super().setUp()
    tmp = tempfile.TemporaryDirectory()
    self.addCleanup(tmp.cleanup)
    self.tmp = tmp.name

  def test_files_convert_as_stored(self):
    """PLY -> .spz -> PLY -> .splat: each file holds the Gaussians of the
    one before, as stored (no turn, no scaling), within the format's
    quantisation; the PLY has the INRIA layout's zero normals."""
    a, b, c, d = (os.path.join(self.tmp, n) for n in (
      'd.spz', 'd.ply', 'sub/d.splat', 'd.compressed.ply'))
    for src, out in ((_DONUT, a), (a, b), (b, c), (b, d)):
      code, stdout, err = _convert(f'--input={src}', f'--out={out}')
      self.assertEqual(code, 0, msg=err)
      self.assertIn('1 file(s)', stdout)
    want = jax.tree.map(np.asarray, ply.load_ply(_DONUT))
    got = spz.load_spz(a)
    np.testing.assert_allclose(got.means, want.means, atol=0.5 / 4096 + 1e-6)
    back = ply.load_ply(b)
    for f in ('means', 'log_scales', 'quats', 'opacity_logits', 'sh'):
      np.testing.assert_array_equal(getattr(back, f), getattr(got, f),
                                    err_msg=f)
    np.testing.assert_array_equal(back.normals, 0.0)
    s = load_splat(c)  # (rows sorted big first, as antimatter15's)
    order = lambda m: np.asarray(m)[np.lexsort(np.asarray(m).T)]  # noqa
    np.testing.assert_allclose(order(s.means), order(back.means), atol=1e-6)
    c = ply.load_ply(d)  # PlayCanvas's: 11-10-11 bits in chunks of 256
    with open(d, 'rb') as f:
      self.assertIn(b'element chunk', f.read(2048))
    self.assertLess(os.path.getsize(d), os.path.getsize(b) / 3)
    np.testing.assert_allclose(c.means, back.means, atol=2e-4)

  def test_a_folder_of_frames_and_bad_arguments(self):
    src, out = os.path.join(self.tmp, 'ply'), os.path.join(self.tmp, 'spz')
    os.makedirs(src)
    frames = []
    for i in range(2):
      g = test_util.random_gaussians(jax.random.PRNGKey(i), 50, 3)
      ply.save_ply(os.path.join(src, f'frame_{i:04d}.ply'), g)
      frames.append(g)
    with open(os.path.join(src, 'notes.txt'), 'w') as f:
      f.write('not a frame')
    code, stdout, err = _convert(f'--input={src}', f'--out={out}',
                                 '--sh_degree=1')
    self.assertEqual(code, 0, msg=err)
    self.assertEqual(sorted(os.listdir(out)),
                     ['frame_0000.spz', 'frame_0001.spz'])
    for i, g in enumerate(frames):
      got = spz.load_spz(os.path.join(out, f'frame_{i:04d}.spz'))
      self.assertEqual(got.sh_degree, 1)
      np.testing.assert_allclose(got.means, g.means, atol=0.5 / 4096 + 1e-6)
    # Bad arguments: one line each, exit 2, nothing written.
    with open(f'{out}/x.spz', 'w') as f:
      f.write('x')
    for args, message in (
        ((f'--input={src}', f'--out={out}/x.spz'),
         'is a file; give a folder'),
        ((f'--input={_DONUT}', f'--out={self.tmp}/d.obj'),
         "unknown scene file type '.obj'"),
        ((f'--input={src}', f'--out={src}', '--out_format=ply'),
         'would overwrite the input'),
        ((f'--input={src}', f'--out={out}', '--input_format=splat'),
         'has no .splat files'),
        ((f'--input={src}', f'--out={out}', '--input_format=compressed'),
         'has no .compressed.ply files'),
        ((f'--input={_DONUT}', f'--out={self.tmp}/e.spz', '--sh_degree=4'),
         '--sh_degree=4: give 0..3')):
      code, _, err = _convert(*args)
      self.assertEqual(code, 2, msg=err)
      self.assertIn(message, err)
    self.assertFalse(os.path.exists(f'{self.tmp}/e.spz'))

  def test_far_centres_and_the_antialiasing_flag(self):
    """Centres 3000 units out take fewer fraction bits (the reference's
    12 reach 2048); .spz to .spz keeps the antialiasing flag, which
    Gaussians do not hold."""
    g = test_util.random_gaussians(jax.random.PRNGKey(3), 40, 1)
    g = g.replace(means=g.means + np.float32([3000.0, -5.0, 0.0]))
    far, aa = os.path.join(self.tmp, 'far.ply'), os.path.join(self.tmp,
                                                             'aa.spz')
    ply.save_ply(far, g)
    spz.save_spz(aa, g.replace(means=g.means - np.float32([3000, 0, 0])),
                 antialiased=True)
    for src, out, extra in ((far, 'far.spz', ()),
                            (aa, 'aa2.spz', ('--spz_version=2',))):
      code, _, err = _convert(f'--input={src}',
                              f'--out={self.tmp}/{out}', *extra)
      self.assertEqual(code, 0, msg=err)
    back = spz.load_spz(os.path.join(self.tmp, 'far.spz'))
    self.assertEqual(spz.read_spz_header(
      os.path.join(self.tmp, 'far.spz')).fractional_bits, 11)
    np.testing.assert_allclose(back.means, g.means, atol=0.5 / 2048 + 4e-4)
    h = spz.read_spz_header(os.path.join(self.tmp, 'aa2.spz'))
    self.assertEqual((h.version, h.antialiased), (2, True))


if __name__ == '__main__':
  absltest.main()
