"""Tests of load_scene / save_scene (physsplat_jax.io.scene)."""

import json
import os
import pathlib
import tempfile

import jax
import jax.numpy as jnp
import numpy as np
from absl.testing import absltest
from absl.testing import parameterized

from physsplat_jax import cameras as cam_lib
from physsplat_jax import scenes
from physsplat_jax import test_util
from physsplat_jax.io.cameras import save_inria_cameras
from physsplat_jax.io.ply import gaussians_to_vertex, load_ply, save_ply
from physsplat_jax.io.ply import write_ply
from physsplat_jax.errors import PhysSplatError
from physsplat_jax.io.scene import SceneFileError, save_scene
from physsplat_jax.scenes import load_scene
from physsplat_jax.io.scene import sidecar_path
from physsplat_jax.io.splat import save_splat
from physsplat_jax.types import ObjectInfo, Scene

DATA = pathlib.Path(__file__).resolve().parent / 'data'


def _assert_scenes_identical(test, a: Scene, b: Scene):
  la, ta = jax.tree.flatten(a)
  lb, tb = jax.tree.flatten(b)
  test.assertEqual(ta, tb)  # includes every static field (objects, names...)
  for i, (x, y) in enumerate(zip(la, lb, strict=True)):
    x, y = np.asarray(x), np.asarray(y)
    test.assertEqual(x.dtype, y.dtype, f'leaf {i}')
    np.testing.assert_array_equal(x, y, err_msg=f'leaf {i}')
  test.assertEqual(a.objects, b.objects)
  test.assertEqual((a.up_axis, a.meters_per_unit, a.name),
                   (b.up_axis, b.meters_per_unit, b.name))
  test.assertEqual([c.name for c in a.cameras], [c.name for c in b.cameras])


def _tiny_scene(ids, cameras=()):
  g = test_util.random_gaussians(jax.random.key(0), len(ids), sh_degree=1)
  return Scene(
    gaussians=g,
    object_ids=jnp.asarray(ids, jnp.int32),
    objects=(ObjectInfo('cup', 'terracotta', True, ('support',)),
             ObjectInfo('jelly', 'jelly')),
    cameras=tuple(cameras),
    up_axis='-y',
    meters_per_unit=0.37,
    name='tiny',
  )


class SceneIOTest(parameterized.TestCase):

  def setUp(self):
    super().setUp()
    self.dir = tempfile.mkdtemp()

  def test_builtin_round_trip_is_exact(self):
    sc = scenes.make_scene('tabletop', detail=0.5, num_cameras=3)
    path = os.path.join(self.dir, 'sub', 'tabletop.ply')
    side = save_scene(path, sc)
    self.assertEqual(side, sidecar_path(path))
    self.assertTrue(os.path.exists(side))
    back = load_scene(path)
    _assert_scenes_identical(self, sc, back)
    # The PLY is a standard 3DGS file with an extra int object_id.
    g = load_ply(path)
    np.testing.assert_array_equal(np.asarray(g.extras['object_id']),
                                  np.asarray(sc.object_ids))

  @parameterized.named_parameters(('_binary', True), ('_ascii', False))
  def test_round_trip_background_ids_sh1(self, binary):
    cams = cam_lib.orbit_cameras((0, 0, 0), 3.0, 10.0, 2, up=(0, -1, 0),
                                 width=40, height=30)
    sc = _tiny_scene([0, 1, -1, 1, 0, -1, 1], cams)
    path = os.path.join(self.dir, 'tiny.ply')
    save_scene(path, sc, binary=binary)
    _assert_scenes_identical(self, sc, load_scene(path))

  def test_round_trip_without_cameras(self):
    sc = _tiny_scene([0, 1, 1])
    path = os.path.join(self.dir, 'nocam.ply')
    save_scene(path, sc)
    back = load_scene(path)
    self.assertEqual(back.cameras, ())
    _assert_scenes_identical(self, sc, back)

  def test_builtin_names(self):
    sc = load_scene('tabletop', detail=0.5, num_cameras=1)
    self.assertEqual(sc.name, 'tabletop')
    self.assertLen(sc.cameras, 1)

  @parameterized.named_parameters(
    ('_udon', 'udon_crop.ply'), ('_train', 'train_1000.ply')
  )
  def test_load_test_data_ply(self, fname):
    path = DATA / fname
    details = {}
    sc = load_scene(path, details=details)
    g = load_ply(path)
    self.assertEqual(sc.gaussians.num, g.num)
    np.testing.assert_array_equal(np.asarray(sc.gaussians.means),
                                  np.asarray(g.means))
    self.assertEqual(sc.objects, (ObjectInfo(fname[:-4]),))
    np.testing.assert_array_equal(np.asarray(sc.object_ids), 0)
    # No cameras: up is the normal of the ground (a general direction, 30+
    # degrees from every axis for these captures), reported.
    self.assertEqual(details['up_source'], 'plane')
    self.assertEqual(sc.up_axis, details['up_axis'])
    self.assertIn(',', sc.up_axis)
    self.assertEqual(load_scene(path, up_axis='z').up_axis, 'z')
    self.assertEqual(sc.meters_per_unit, 1.0)
    self.assertLen(sc.cameras, 8)
    # Fitted cameras see the (robust) centre of the scene.
    lo, hi = np.percentile(np.asarray(g.means), [1, 99], axis=0)
    for cam in sc.cameras:
      (u, v), z = (np.asarray(x) for x in cam.project(0.5 * (lo + hi)))
      self.assertGreater(z, 0)
      np.testing.assert_allclose([u, v], [cam.width / 2, cam.height / 2],
                                 atol=1e-2)
    sc2 = load_scene(path, num_cameras=2, width=64, height=48,
                     up_axis='-y', meters_per_unit=0.5)
    self.assertLen(sc2.cameras, 2)
    self.assertEqual((sc2.cameras[0].width, sc2.cameras[0].height), (64, 48))
    self.assertEqual((sc2.up_axis, sc2.meters_per_unit), ('-y', 0.5))

  def test_object_id_property(self):
    g = test_util.random_gaussians(jax.random.key(1), 6)
    seg = jnp.asarray([7.0, 3.0, 3.0, -1.0, 7.0, 3.0], jnp.float32)
    g = g.replace(extras={'segment': seg, 'confidence': jnp.ones(6)})
    path = os.path.join(self.dir, 'seg.ply')
    save_ply(path, g)
    sc = load_scene(path)
    np.testing.assert_array_equal(np.asarray(sc.object_ids),
                                  [1, 0, 0, -1, 1, 0])
    self.assertEqual([o.name for o in sc.objects], ['object_3', 'object_7'])
    self.assertEqual(sc.objects[0].tags, ('ply_id=3',))
    self.assertEqual(sorted(sc.gaussians.extras), ['confidence'])
    # Ignoring the ids, or naming another property.
    sc = load_scene(path, object_property=False)
    np.testing.assert_array_equal(np.asarray(sc.object_ids), 0)
    self.assertIn('segment', sc.gaussians.extras)
    sc = load_scene(path, object_property='confidence')  # all 1.0
    np.testing.assert_array_equal(np.asarray(sc.object_ids), 0)
    self.assertEqual([o.name for o in sc.objects], ['object_1'])

  def test_object_id_int_property_named_object_id(self):
    g = test_util.random_gaussians(jax.random.key(2), 4)
    g = g.replace(extras={'object_id': jnp.asarray([0, 1, 2, 1], jnp.int32)})
    path = os.path.join(self.dir, 'ids.ply')
    save_ply(path, g)
    sc = load_scene(path)
    np.testing.assert_array_equal(np.asarray(sc.object_ids), [0, 1, 2, 1])
    self.assertEqual(sc.num_objects, 3)
    self.assertEqual(sc.gaussians.extras, {})

  def test_non_integer_ids(self):
    g = test_util.random_gaussians(jax.random.key(3), 3)
    g = g.replace(extras={'label': jnp.asarray([0.5, 1.0, 2.0])})
    path = os.path.join(self.dir, 'frac.ply')
    save_ply(path, g)
    with self.assertRaisesRegex(SceneFileError, "'label'.*non-integer"):
      load_scene(path)

  def test_cameras_json_next_to_file_sets_cameras_and_up(self):
    g = test_util.random_gaussians(jax.random.key(4), 50)
    path = os.path.join(self.dir, 'cap.ply')
    save_ply(path, g)
    # A capture shot upright in a -y-up world (typical COLMAP).
    cams = cam_lib.orbit_cameras((0, 0, 0), 4.0, 20.0, 5, up=(0, -1, 0),
                                 width=80, height=60)
    cams = [c.replace(name=f'img_{i}') for i, c in enumerate(cams)]
    save_inria_cameras(os.path.join(self.dir, 'cameras.json'), cams)
    sc = load_scene(path)
    self.assertEqual([c.name for c in sc.cameras],
                     [f'img_{i}' for i in range(5)])
    np.testing.assert_allclose(np.asarray(sc.cameras[2].viewmat),
                               np.asarray(cams[2].viewmat), atol=1e-5)
    self.assertEqual(sc.up_axis, '-y')
    self.assertEqual(load_scene(path, up_axis='z').up_axis, 'z')
    # cameras=False skips the file and fits an orbit.
    fitted = load_scene(path, cameras=False, num_cameras=3)
    self.assertEqual(fitted.cameras[0].name, 'orbit_0000')
    self.assertEqual(fitted.up_axis, 'z')

  def test_inria_output_folder(self):
    g = test_util.random_gaussians(jax.random.key(5), 20)
    for it, n in ((7000, 10), (30000, 20)):
      save_ply(os.path.join(self.dir, 'point_cloud', f'iteration_{it}',
                            'point_cloud.ply'), g.subset(np.arange(n)))
    cams = cam_lib.orbit_cameras((0, 0, 0), 4.0, 20.0, 2, width=32,
                                 height=32)
    save_inria_cameras(os.path.join(self.dir, 'cameras.json'), cams)
    sc = load_scene(self.dir)
    self.assertEqual(sc.gaussians.num, 20)  # the latest iteration
    self.assertLen(sc.cameras, 2)
    self.assertEqual(sc.up_axis, 'z')

  def test_a_folder_with_only_the_training_input(self):
    # input.ply was read as the scene: "missing properties f_dc_0, ...".
    with open(os.path.join(self.dir, 'input.ply'), 'w') as fh:
      fh.write('ply\nformat ascii 1.0\nelement vertex 0\nend_header\n')
    with self.assertRaisesRegex(SceneFileError, 'holds only input.ply, the '
                                'point cloud 3DGS training starts from'):
      load_scene(self.dir)

  def test_positions_too_far_to_frame_name_the_file(self):
    # The camera fit's error named no file.
    g = test_util.random_gaussians(jax.random.key(7), 10)
    path = os.path.join(self.dir, 'far.ply')
    save_ply(path, g.replace(means=g.means * 1e13 + 1e13))
    with self.assertRaisesRegex(SceneFileError, r'far\.ply: cannot fit a '
                                r'camera .* beyond 1e\+12 scene units'):
      load_scene(path)

  def test_splat_file(self):
    g = test_util.random_gaussians(jax.random.key(6), 10)
    path = os.path.join(self.dir, 'x.splat')
    save_splat(path, g)
    sc = load_scene(path, num_cameras=1)
    self.assertEqual(sc.gaussians.num, 10)
    self.assertEqual(sc.objects[0].name, 'x')

  def test_zero_image_size_is_refused(self):
    # width=0 was taken for "unset": a 384-pixel-wide camera, no word.
    ply = str(DATA / 'train_1000.ply')
    for kw, want in ((dict(width=0, height=10), 'width=0'),
                     (dict(width=10, height=0), 'height=0'),
                     (dict(width=-3), 'width=-3')):
      with self.subTest(want), self.assertRaisesRegex(
          SceneFileError, want + r'; the image size must be >= 1 pixel'):
        load_scene(ply, num_cameras=1, **kw)
    cam = load_scene(ply, num_cameras=1, width=10, height=8).cameras[0]
    self.assertEqual((cam.width, cam.height), (10, 8))

  def test_errors(self):
    with self.assertRaisesRegex(SceneFileError,
                                'built-in scene .donut, ficus, tabletop'):
      load_scene('teapot')
    with self.assertRaisesRegex(SceneFileError, "did you mean 'tabletop'"):
      load_scene('tabletopp')
    g = load_ply(DATA / 'udon_crop.ply')
    nan = os.path.join(self.dir, 'nan.ply')
    vertex = dict(gaussians_to_vertex(g))
    vertex['x'] = vertex['x'].copy()
    vertex['x'][2] = np.nan  # save_ply refuses this; a broken file has it
    write_ply(nan, {'vertex': vertex})
    with self.assertRaisesRegex(PhysSplatError, 'non-finite.*1 of'):
      load_scene(nan)
    empty = os.path.join(self.dir, 'empty.ply')
    write_ply(empty, {'vertex': {k: v[:0] for k, v in vertex.items()}})
    with self.assertRaisesRegex(PhysSplatError, 'no Gaussians|0 vertices'):
      load_scene(empty)
    huge = os.path.join(self.dir, 'huge.ply')
    save_ply(huge, g.replace(log_scales=g.log_scales.at[:5].set(10.0)))
    with self.assertLogs(level='WARNING') as logs:
      load_scene(huge, num_cameras=1)
    self.assertIn('5 of', ' '.join(logs.output))
    # One Gaussian (no extent): loads with cameras around it (the camera
    # fit failed in look_at, naming no file).
    one = os.path.join(self.dir, 'one.ply')
    save_ply(one, g.subset(np.arange(g.num) == 0))
    self.assertLen(load_scene(one, num_cameras=2).cameras, 2)
    # All transparent: a video of only the background, said at load.
    clear = os.path.join(self.dir, 'clear.ply')
    save_ply(clear, g.replace(opacity_logits=jnp.full_like(g.opacity_logits,
                                                           -50.0)))
    with self.assertLogs(level='WARNING') as logs:
      load_scene(clear, num_cameras=1)
    self.assertIn('every Gaussian is transparent', ' '.join(logs.output))
    with self.assertRaisesRegex(SceneFileError, 'donut, ficus, tabletop'):
      load_scene(os.path.join(self.dir, 'missing.ply'))
    with self.assertRaisesRegex(SceneFileError, 'name or a path'):
      load_scene(3)
    obj = os.path.join(self.dir, 'mesh.obj')
    pathlib.Path(obj).write_text('v 0 0 0\n')
    with self.assertRaisesRegex(SceneFileError, r"'\.obj'.*\.ply"):
      load_scene(obj)
    with self.assertRaisesRegex(SceneFileError, 'no point_cloud'):
      load_scene(self.dir)
    ply = str(DATA / 'train_1000.ply')
    with self.assertRaisesRegex(TypeError, 'unknown option.*detail'):
      load_scene(ply, detail=2)
    with self.assertRaisesRegex(ValueError, 'up axis'):
      load_scene(ply, up_axis='w')
    with self.assertRaisesRegex(SceneFileError, 'meters_per_unit'):
      load_scene(ply, meters_per_unit=0)
    with self.assertRaisesRegex(SceneFileError, "'nope' is not a property"):
      load_scene(ply, object_property='nope')
    sc = _tiny_scene([0, 1, 0])
    with self.assertRaisesRegex(SceneFileError, r'\.ply'):
      save_scene(os.path.join(self.dir, 'a.splat'), sc)
    with self.assertRaisesRegex(SceneFileError, 'ids must be -1 or 0..1'):
      save_scene(os.path.join(self.dir, 'a.ply'),
                 sc.replace(object_ids=jnp.asarray([0, 2, 0], jnp.int32)))
    # A bad sidecar is named in the error.
    path = os.path.join(self.dir, 'b.ply')
    save_scene(path, sc)
    with open(sidecar_path(path), 'w') as f:
      json.dump({'hello': 1}, f)
    with self.assertRaisesRegex(SceneFileError, r'b\.scene\.json.*sidecar'):
      load_scene(path)
    with open(sidecar_path(path), 'w') as f:
      f.write('{not json')
    with self.assertRaisesRegex(SceneFileError, 'cannot read'):
      load_scene(path)

  # Rule breaks from review: raw errors and silent wrong values.

  def _saved(self, name='s.ply'):
    cams = cam_lib.orbit_cameras((0, 0, 0), 3.0, 10.0, 2, width=40,
                                 height=30)
    path = os.path.join(self.dir, name)
    save_scene(path, _tiny_scene([0, 1, 0], cams))
    with open(sidecar_path(path)) as f:
      return path, json.load(f)

  @parameterized.named_parameters(
    ('_version_text', ('version',), 'abc', r'version = "abc"; must be a '
     'whole number'),
    ('_version_null', ('version',), None, r'version = null'),
    ('_mpu_text', ('meters_per_unit',), 'abc',
     r'meters_per_unit = "abc"; must be a finite number > 0'),
    ('_mpu_negative', ('meters_per_unit',), -1, r'meters_per_unit = -1;'),
    ('_mpu_nan', ('meters_per_unit',), float('nan'), r'meters_per_unit = NaN'),
    ('_up_number', ('up_axis',), 3, r'up_axis = 3; must be a string'),
    ('_up_bad', ('up_axis',), 'w', r'up_axis = "w"; up axis .w. is not'),
    ('_name', ('name',), 5, r'name = 5; must be a string'),
    ('_id_property', ('id_property',), [1], r'id_property = \[1\]'),
    ('_fixed', ('objects', 0, 'fixed'), 'false',
     r'objects\[0\]\.fixed = "false"; must be true or false'),
    ('_tags', ('objects', 0, 'tags'), 'abc',
     r'objects\[0\]\.tags = "abc"; must be a list of strings'),
    ('_fx', ('cameras', 0, 'fx'), 'abc', r'cameras\[0\]\.fx = "abc"; must '
     'be a finite number > 0'),
    ('_width_text', ('cameras', 1, 'width'), 'abc',
     r'cameras\[1\]\.width = "abc"; must be a whole number >= 1'),
    ('_width_fraction', ('cameras', 0, 'width'), 40.5,
     r'cameras\[0\]\.width = 40.5'),
    ('_dtype', ('cameras', 0, 'dtype'), 'banana',
     r'cameras\[0\]\.dtype = "banana"; must be one of float32'),
    ('_dtype_int', ('cameras', 0, 'dtype'), 'int32',
     r'cameras\[0\]\.dtype = "int32"'),
    ('_viewmat', ('cameras', 0, 'viewmat'), 'eye',
     r'cameras\[0\]\.viewmat = "eye"; must be a 4x4'),
    ('_viewmat_ragged', ('cameras', 0, 'viewmat'), [[1, 0], [0]],
     r'cameras\[0\]\.viewmat = \[\[1, 0\], \[0\]\]'),
    ('_near', ('cameras', 0, 'near'), 'abc', r'cameras\[0\]\.near = "abc"'),
    ('_cx_nan', ('cameras', 0, 'cx'), float('nan'),
     r'cameras\[0\]\.cx = NaN; must be a finite number'),
    ('_near_far', ('cameras', 0, 'near'), 1e11,
     r'cameras\[0\]: camera .* need 0 < near < far'),
  )
  def test_bad_sidecar_fields_are_named(self, keys, value, want):
    path, side = self._saved()
    d = side
    for k in keys[:-1]:
      d = d[k]
    d[keys[-1]] = value
    with open(sidecar_path(path), 'w') as f:
      json.dump(side, f)
    with self.assertRaisesRegex(
        SceneFileError, r's\.scene\.json: ' + want + r'.*delete s\.scene'):
      load_scene(path)

  def test_save_scene_refuses_what_load_would_refuse(self):
    sc = _tiny_scene([0, 1, 0])
    path = os.path.join(self.dir, 'n.ply')
    with self.assertRaisesRegex(
        SceneFileError, r"save_scene\('.*n\.ply'\): scene\.meters_per_unit "
        r'= NaN; must be a finite number > 0'):
      save_scene(path, sc.replace(meters_per_unit=float('nan')))
    with self.assertRaisesRegex(SceneFileError, r'scene\.up_axis = "w"'):
      save_scene(path, sc.replace(up_axis='w'))
    self.assertEqual(os.listdir(self.dir), [])  # nothing written

  def test_save_scene_checks_both_outputs_first(self):
    sc = _tiny_scene([0, 1, 0])
    os.mkdir(os.path.join(self.dir, 'd.ply'))
    with self.assertRaisesRegex(SceneFileError, r'd\.ply: is a directory'):
      save_scene(os.path.join(self.dir, 'd.ply'), sc)
    os.mkdir(os.path.join(self.dir, 'x.scene.json'))
    with self.assertRaisesRegex(
        SceneFileError, r'x\.scene\.json: is a directory; give the scene '
        'sidecar file.s path'):
      save_scene(os.path.join(self.dir, 'x.ply'), sc)
    self.assertFalse(os.path.exists(os.path.join(self.dir, 'x.ply')))
    pathlib.Path(self.dir, 'f').write_text('')
    with self.assertRaisesRegex(SceneFileError, r'f is a file, not a folder'):
      save_scene(os.path.join(self.dir, 'f', 'y.ply'), sc)

  def test_found_camera_files_do_not_block_loading(self):
    g = test_util.random_gaussians(jax.random.key(7), 20)
    path = os.path.join(self.dir, 'c.ply')
    save_ply(path, g)
    # An unrelated transforms_*.json is not taken for cameras.
    pathlib.Path(self.dir, 'transforms_config.json').write_text('{"a": 1}')
    self.assertEqual(load_scene(path, num_cameras=2).cameras[0].name,
                     'orbit_0000')
    # A bad cameras.json found automatically: the error says so.
    pathlib.Path(self.dir, 'cameras.json').write_text('{"a": 1}')
    with self.assertRaisesRegex(
        SceneFileError, r'cameras\.json was found next to it automatically '
        r'.*unknown camera file.*fix that file or move it away.*'
        'cameras=False'):
      load_scene(path)
    self.assertLen(load_scene(path, cameras=False, num_cameras=2).cameras, 2)

  @parameterized.named_parameters(
    ('_width_text', dict(width='abc'), r"width='abc'; the image size"),
    ('_width_fraction', dict(width=64.5), r'width=64\.5; the image size'),
    ('_num_cameras_text', dict(num_cameras='abc'), r"num_cameras='abc'"),
    ('_num_cameras_fraction', dict(num_cameras=2.7),
     r'num_cameras=2\.7; must be a whole number >= 1'),
    ('_mpu_text', dict(meters_per_unit='abc'),
     r"meters_per_unit='abc'; must be a finite number > 0"),
    ('_up_number', dict(up_axis=2), r'up_axis=2; must be a string'),
    ('_dtype_int', dict(dtype=jnp.int32), r'dtype=.*int32.*float dtype'),
    ('_cameras_fd', dict(cameras=5), r'cameras=5; give a camera file path'),
    ('_fov', dict(fov_deg='wide'), r"fov_deg='wide'"),
    ('_name', dict(name=3), r'name=3; must be a string'),
  )
  def test_bad_option_values_are_named(self, options, want):
    with self.assertRaisesRegex(SceneFileError,
                                r"load_scene\('.*train_1000\.ply'\): " + want):
      load_scene(DATA / 'train_1000.ply', **options)


if __name__ == '__main__':
  absltest.main()
