"""Segmentation inputs from files (io.segment_inputs) and the script flags
that take them (experiments.simulate --masks / --boxes)."""

import json
import os
import subprocess
import sys
import tempfile

import numpy as np
from absl.testing import absltest
from PIL import Image

from physsplat_jax import segmentation as seg
from physsplat_jax.cameras import orbit_cameras
from physsplat_jax.io import segment_inputs as si
from physsplat_jax.io.cameras import save_inria_cameras
from physsplat_jax.io.ply import save_ply
from physsplat_jax.pipeline import job
from physsplat_jax.render.reference import render_reference
from physsplat_jax.types import concatenate_gaussians
from physsplat_jax.types import make_camera

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from segmentation_test import _blob  # noqa: E402
from segmentation_test import _gaussians  # noqa: E402

_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _cameras(names, width=8, height=6):
  return [make_camera(np.eye(4), 10.0, 10.0, width, height, name=n)
          for n in names]


def _tempdir(test):
  d = tempfile.TemporaryDirectory()
  test.addCleanup(d.cleanup)
  return d.name


def _palette_png(path, a):
  """An indexed PNG with distinct colours (as DAVIS / SAM trackers write)."""
  im = Image.fromarray(a.astype(np.uint8), mode='P')
  im.putpalette([v for i in range(256) for v in (
    (i * 37) % 256, (i * 91) % 256, (i * 53) % 256)])
  im.save(path)


def _png(path, a, mode):
  Image.fromarray(a.astype(np.uint16 if mode == 'I;16' else np.uint8),
                  mode=None if mode == 'I;16' else mode).save(path)


class MaskFilesTest(absltest.TestCase):

  def setUp(self):
    super().setUp()
    self.dir = _tempdir(self)

  def test_label_images_pair_with_cameras_by_name(self):
    cams = _cameras(['shots/IMG_1.jpg', 'IMG_2.jpg', 'IMG_3', 'IMG_4'])
    a = np.zeros((6, 8), np.int64)
    a[1:3, 1:3], a[4:, 5:] = 3, 7
    _palette_png(os.path.join(self.dir, 'IMG_2.png'), a)
    Image.fromarray(a.astype(np.uint16)).save(
      os.path.join(self.dir, 'IMG_1.png'))  # 16-bit grey
    np.save(os.path.join(self.dir, 'IMG_3.npy'), a)
    _png(os.path.join(self.dir, 'notes.png'), a, 'L')  # names no camera
    with self.assertLogs(level='WARNING') as logs:
      got_cams, masks, names = si.load_masks(self.dir, cams)
    self.assertRegex(logs.output[0], r'1 file\(s\) .* notes\.png')
    # IMG_4 has no mask: not used.
    self.assertEqual([c.name for c in got_cams],
                     ['shots/IMG_1.jpg', 'IMG_2.jpg', 'IMG_3'])
    self.assertEqual(names, ('mask_3', 'mask_7'))
    want = np.where(a == 3, 0, np.where(a == 7, 1, -1))
    for m in masks:
      self.assertEqual(m.dtype, np.int32)
      np.testing.assert_array_equal(m, want)
    _, _, names = si.load_masks(self.dir, cams, names=['cup', 'plate'])
    self.assertEqual(names, ('cup', 'plate'))
    with self.assertRaisesRegex(si.SegmentInputError,
                                r'1 mask names for 2 objects .*mask_3'):
      si.load_masks(self.dir, cams, names=['cup'])

  def test_colour_masks_give_one_object_per_colour_in_every_view(self):
    cams = _cameras(['a', 'b'])
    red, green = (255, 0, 0), (0, 200, 0)
    x = np.zeros((6, 8, 4), np.uint8)
    x[..., 3] = 255
    x[0, 0, :3], x[5, 7, :3] = red, green
    y = x.copy()
    y[0, 0, :3], y[5, 7, :3] = green, red
    y[2, 2] = (0, 200, 0, 0)  # transparent: no object
    Image.fromarray(x, 'RGBA').save(os.path.join(self.dir, 'a.png'))
    Image.fromarray(y, 'RGBA').save(os.path.join(self.dir, 'b.png'))
    _, (ma, mb), names = si.load_masks(self.dir, cams)
    self.assertLen(names, 2)
    self.assertEqual(ma[0, 0], mb[5, 7])
    self.assertEqual(ma[5, 7], mb[0, 0])
    self.assertNotEqual(ma[0, 0], ma[5, 7])
    self.assertEqual((ma >= 0).sum() + (mb >= 0).sum(), 4)
    self.assertIn('colour_ff0000', names)

  def test_order_when_no_file_is_named_after_a_camera_and_errors(self):
    cams = _cameras(['IMG_1', 'IMG_2'])
    a = np.zeros((6, 8), np.uint8)
    a[0, 0] = 1
    _png(os.path.join(self.dir, 'm0.png'), a, 'L')
    _png(os.path.join(self.dir, 'm1.png'), 2 * a, 'L')
    got, masks, names = si.load_masks(self.dir, cams)
    self.assertEqual([c.name for c in got], ['IMG_1', 'IMG_2'])
    self.assertEqual(names, ('mask_1', 'mask_2'))
    self.assertEqual((masks[0][0, 0], masks[1][0, 0]), (0, 1))
    with self.assertRaisesRegex(
        si.SegmentInputError, r"none of the 2 files .* of the scene's 3 "
        r'cameras \(IMG_1, IMG_2, IMG_3\): name each mask after'):
      si.load_masks(self.dir, _cameras(['IMG_1', 'IMG_2', 'IMG_3']))
    x = np.zeros((6, 8, 3), np.uint8)
    x[1, 1] = (9, 80, 200)
    Image.fromarray(x).save(os.path.join(self.dir, 'm2.png'))
    with self.assertRaisesRegex(si.SegmentInputError, 'mix single-channel'):
      si.load_masks(self.dir, _cameras(['m0', 'm1', 'm2']))
    empty = _tempdir(self)
    with self.assertRaisesRegex(si.SegmentInputError, 'holds no label'):
      si.load_masks(empty, cams)
    with self.assertRaisesRegex(si.SegmentInputError, 'does not exist'):
      si.load_masks(os.path.join(empty, 'nope'), cams)
    with self.assertRaisesRegex(si.SegmentInputError, 'has no cameras'):
      si.load_masks(self.dir, [])
    np.save(os.path.join(empty, 'IMG_1.npy'), np.full((6, 8), -2))
    with self.assertRaisesRegex(si.SegmentInputError, r'holds -2; mask '
                                r'values are 0 \(no object\)'):
      si.load_masks(empty, cams)
    np.save(os.path.join(empty, 'IMG_1.npy'), np.zeros((6, 8), np.int64))
    with self.assertRaisesRegex(si.SegmentInputError, 'mark no object'):
      si.load_masks(empty, cams)
    np.save(os.path.join(empty, 'IMG_1.npy'), np.zeros((6, 8)))
    with self.assertRaisesRegex(si.SegmentInputError, 'integer array'):
      si.load_masks(empty, cams)


class BoxesFileTest(absltest.TestCase):

  def test_boxes_names_fixed_and_errors(self):
    path = os.path.join(_tempdir(self), 'boxes.json')

    def write(data):
      with open(path, 'w', encoding='utf-8') as f:
        json.dump(data, f)

    write({'objects': [{'name': 'cup', 'box': [0, 1, 0, 1, 0, 1]},
                       {'name': 'table', 'box': [-2, 2, -2, 2, -1, 0],
                        'fixed': True}]})
    got = si.load_boxes(path)
    self.assertEqual(got['names'], ('cup', 'table'))
    self.assertEqual(got['fixed'], (False, True))
    np.testing.assert_array_equal(got['boxes'][1], [-2, 2, -2, 2, -1, 0])
    write([{'box': [0, 1, 0, 1, 0, 1]}])  # a bare list, default names
    self.assertEqual(si.load_boxes(path)['names'], ('box_0',))
    for data, msg in (
        ([{'name': 'a'}], 'object 0 has no "box"'),
        ([{'box': [0, 1, 0, 1]}], r'not 6 finite numbers'),
        ([{'box': [1, 0, 0, 1, 0, 1]}], 'min above its max'),
        ([{'box': [0, 1] * 3, 'fixed': 'yes'}], '"fixed" is \'yes\''),
        ([{'name': 'a', 'box': [0, 1] * 3}] * 2, "two objects are named 'a'"),
        ({}, 'expected a list of objects')):
      write(data)
      with self.subTest(msg), self.assertRaisesRegex(si.SegmentInputError,
                                                     msg):
        si.load_boxes(path)
    with open(path, 'w', encoding='utf-8') as f:
      f.write('{not json')
    with self.assertRaisesRegex(si.SegmentInputError, 'not JSON'):
      si.load_boxes(path)
    with self.assertRaisesRegex(si.SegmentInputError, 'No such file'):
      si.load_boxes(path + '.missing')


def _two_blob_capture(folder):
  """A floor and two blobs saved as an INRIA output folder with three
  cameras, and palette masks of the blobs (1, 2; the floor 0) named after
  the cameras' images. Returns the ground-truth object ids (-1 floor)."""
  rng = np.random.default_rng(0)
  floor = np.c_[rng.uniform(-1, 1, (200, 2)), np.zeros(200)]
  a = _blob(rng, (0.4, 0.0, 0.25), 80, 0.2)
  b = _blob(rng, (-0.4, 0.1, 0.25), 80, 0.2)
  gt = np.r_[-np.ones(200), np.zeros(80), np.ones(80)].astype(int)
  g = concatenate_gaussians([
    _gaussians(floor, (0.5, 0.5, 0.5), opacity_logit=2.0),
    _gaussians(a, (1, 0, 0), opacity_logit=2.0),
    _gaussians(b, (0, 0, 1), opacity_logit=2.0)])
  cams = orbit_cameras((0, 0, 0.1), 2.5, 45.0, 3, width=48, height=48)
  cams = [c.replace(name=f'frame_{i:03d}.jpg') for i, c in enumerate(cams)]
  save_ply(os.path.join(folder, 'point_cloud', 'iteration_30000',
                        'point_cloud.ply'), g)
  save_inria_cameras(os.path.join(folder, 'cameras.json'), cams)
  os.makedirs(os.path.join(folder, 'masks'))
  onehot = np.eye(3)[gt + 1]
  for cam in cams:
    img, alpha, _ = render_reference(
      np.asarray(g.means), np.asarray(g.covariances), onehot,
      np.asarray(g.opacities), np.asarray(cam.viewmat), cam.fx, cam.fy,
      cam.cx, cam.cy, 48, 48, cam.near, cam.far)
    share = img.max(-1) / np.maximum(alpha, 1e-9)
    m = np.where((alpha > 0.5) & (share > 0.6), img.argmax(-1), 0)
    _palette_png(os.path.join(folder, 'masks',
                              cam.name.replace('.jpg', '.png')), m)
  return gt


class MasksThroughThePipelineTest(absltest.TestCase):

  def test_segment_stage_lifts_the_folder_with_the_scenes_cameras(self):
    from physsplat_jax import scenes
    d = _tempdir(self)
    gt = _two_blob_capture(d)
    scene = scenes.load_scene(d)
    cams, masks, names = si.load_masks(os.path.join(d, 'masks'),
                                       scene.cameras, ['red', 'blue'])
    out = job.segment_stage(scene, 'masks', masks=masks, names=names)
    self.assertEqual([o.name for o in out.objects], ['red', 'blue'])
    ids = np.asarray(out.object_ids)
    self.assertGreater(np.mean(ids == gt), 0.95)
    # The same through segmentation.segment with the cameras given.
    direct = seg.segment(scene.gaussians, 'auto', cameras=cams, masks=masks,
                         names=names)
    np.testing.assert_array_equal(direct.object_ids, ids)

  def test_segment_stage_takes_a_boxes_file(self):
    from physsplat_jax import scenes
    d = _tempdir(self)
    gt = _two_blob_capture(d)
    path = os.path.join(d, 'boxes.json')
    with open(path, 'w', encoding='utf-8') as f:
      json.dump([{'name': 'red', 'box': [0.15, 0.65, -0.25, 0.25, 0.0, 0.5]},
                 {'name': 'floor', 'box': [-1, 1, -1, 1, -0.01, 0.01],
                  'fixed': True}], f)
    out = job.segment_stage(scenes.load_scene(d), 'boxes',
                            **si.load_boxes(path))
    self.assertEqual([(o.name, o.fixed) for o in out.objects],
                     [('red', False), ('floor', True)])
    ids = np.asarray(out.object_ids)
    np.testing.assert_array_equal(ids[:200], 1)
    np.testing.assert_array_equal(ids[gt == 0], 0)
    np.testing.assert_array_equal(ids[gt == 1], -1)

  def test_attribute_and_auto_keep_the_ids_the_file_gave(self):
    # load_scene moves the object-id property into object_ids: 'attribute'
    # then found none and 'auto' re-segmented geometrically.
    from physsplat_jax import scenes
    d = _tempdir(self)
    _two_blob_capture(d)
    ply = os.path.join(d, 'point_cloud', 'iteration_30000', 'point_cloud.ply')
    from physsplat_jax.io.ply import load_ply
    g = load_ply(ply)
    ids = np.r_[np.zeros(200), np.ones(80), 2 * np.ones(80)].astype(np.int32)
    save_ply(ply, g.replace(extras={'object_id': ids}))
    scene = scenes.load_scene(d)
    for method in ('attribute', 'auto'):
      out = job.segment_stage(scene, method)
      self.assertLen(out.objects, 3, method)
      np.testing.assert_array_equal(np.asarray(out.object_ids), ids)
    bare = scene.replace(object_ids=np.zeros(360, np.int32),
                         objects=scene.objects[:1])
    bare = bare.replace(objects=(bare.objects[0].__class__('bare'),))
    with self.assertRaisesRegex(seg.SegmentationError,
                                'no object-id property'):
      job.segment_stage(bare, 'attribute')

  def test_masks_on_a_scene_without_cameras_are_refused(self):
    # load_scene fits an orbit to a bare PLY: masks paired with it in
    # sorted order would have labelled the Gaussians at random.
    from experiments.lib import simulate as lib
    from physsplat_jax import pipeline as pl
    d = _tempdir(self)
    _two_blob_capture(d)
    os.makedirs(os.path.join(d, 'alone'))
    bare = os.path.join(d, 'alone', 'bare.ply')  # no cameras.json beside
    os.rename(os.path.join(d, 'point_cloud', 'iteration_30000',
                           'point_cloud.ply'), bare)
    with self.assertRaisesRegex(pl.PipelineError, r'has no cameras of its '
                                r'own \(an orbit was fitted\)'):
      lib.run_scene(bare, pl.PipelineConfig(num_frames=1),
                    os.path.join(d, 'out'), segment='masks',
                    masks=os.path.join(d, 'masks'))

  def test_the_script_simulates_the_objects_its_masks_name(self):
    with tempfile.TemporaryDirectory() as d:
      gt = _two_blob_capture(d)
      out = os.path.join(d, 'out')
      base = [sys.executable, '-m', 'experiments.simulate', f'--scene={d}',
              f'--out={out}', f'--compile_cache={d}/cache']
      proc = subprocess.run(
        base + [f'--masks={d}/masks', '--mask_names=red,blue',
                '--config.num_frames=1', '--config.grid_res=16',
                '--config.render=none', '--config.max_particles=600'],
        capture_output=True, text=True, check=False, timeout=300,
        cwd=_ROOT)
      self.assertEqual(proc.returncode, 0, proc.stderr[-2000:])
      report = json.load(open(os.path.join(out, 'report.json')))
      self.assertEqual([o['name'] for o in report['objects']],
                       ['red', 'blue'])
      lifted = [o['num_gaussians'] for o in report['objects']]
      np.testing.assert_allclose(lifted, [(gt == 0).sum(), (gt == 1).sum()],
                                 rtol=0.05)
      proc = subprocess.run(base + ['--segment=masks'], capture_output=True,
                            text=True, check=False, timeout=120, cwd=_ROOT)
      self.assertNotEqual(proc.returncode, 0)
      self.assertIn('--segment=masks needs --masks=FOLDER', proc.stderr)


if __name__ == '__main__':
  absltest.main()
