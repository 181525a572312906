"""Tests of the built-in scenes and the mesh -> Gaussians converter."""

import functools
import math

import jax
import numpy as np
import trimesh
from absl.testing import absltest
from absl.testing import parameterized

from physsplat_jax import scenes
from physsplat_jax.io.ply import load_ply
from physsplat_jax.scenes import donut as donut_mod
from physsplat_jax.scenes import tabletop as tabletop_mod
from physsplat_jax.scenes.mesh import MeshError, gaussians_from_mesh

MATERIALS = frozenset({
  'terracotta', 'soil', 'plant_stem', 'leaf', 'wood', 'jelly', 'rubber',
  'sand', 'aluminum', 'dough',
})  # fmt: skip
# name -> (object name, material, fixed) in order.
EXPECTED = {
  'tabletop': [('table top', 'wood', True), ('jelly cube', 'jelly', False),
               ('rubber ball', 'rubber', False),
               ('sand pile', 'sand', False), ('metal can', 'aluminum', False)],
  'ficus': [('pot', 'terracotta', True), ('soil', 'soil', True),
            ('stem', 'plant_stem', False), ('leaves', 'leaf', False)],
  'donut': [('donut', 'dough', False), ('wooden board', 'wood', True)],
}  # fmt: skip
MPU = {'tabletop': 1.0, 'ficus': 1.0, 'donut': 0.45}
# Unit-quaternion tolerance (float32).
_QUAT_TOL = 1e-5
# Gaussian centres of a resting object lie this far above the support at most
# [scene units].
_MAX_REST_GAP = 0.005
NUM_CAMERAS = 2


@functools.lru_cache(maxsize=None)
def _scene(name, seed=0):
  return scenes.make_scene(name, seed=seed, num_cameras=NUM_CAMERAS)


def _arrays(scene):
  return [np.asarray(x) for x in jax.tree.leaves(scene)]


def _part(scene, name):
  m = np.asarray(scene.object_mask(name))
  return np.asarray(scene.gaussians.means)[m]


class BuiltinScenesTest(parameterized.TestCase):

  def test_registry(self):
    self.assertEqual(scenes.list_scenes(), ('donut', 'ficus', 'tabletop'))
    self.assertEqual(scenes.DEFAULT_SCENE, 'tabletop')
    with self.assertRaisesRegex(ValueError, 'donut, ficus, tabletop'):
      scenes.make_scene('teapot')
    with self.assertRaisesRegex(TypeError, 'detail'):
      scenes.make_scene('tabletop', resolution=3)
    with self.assertRaisesRegex(ValueError, 'detail'):
      scenes.make_scene('tabletop', detail=0.0)

  @parameterized.named_parameters(
    ('_tabletop', 'tabletop'), ('_ficus', 'ficus'), ('_donut', 'donut')
  )
  def test_deterministic(self, name):
    a = _scene(name)
    b = scenes.make_scene(name, seed=0, num_cameras=NUM_CAMERAS)
    for x, y in zip(_arrays(a), _arrays(b), strict=True):
      np.testing.assert_array_equal(x, y)
      self.assertEqual(x.dtype, y.dtype)
    self.assertEqual(a.objects, b.objects)
    c = scenes.make_scene(name, seed=1, num_cameras=0)
    self.assertEqual(len(c.cameras), 0)
    # Another seed changes the procedural Gaussians.
    mc = np.asarray(c.gaussians.means)
    ma = np.asarray(a.gaussians.means)
    self.assertFalse(mc.shape == ma.shape and np.array_equal(mc, ma))

  @parameterized.named_parameters(
    ('_tabletop', 'tabletop'), ('_ficus', 'ficus'), ('_donut', 'donut')
  )
  def test_objects_and_parameters(self, name):
    sc = _scene(name)
    got = [(o.name, o.material, o.fixed) for o in sc.objects]
    self.assertEqual(got, EXPECTED[name])
    self.assertTrue({o.material for o in sc.objects} <= MATERIALS)
    self.assertEqual(sc.up_axis, 'z')
    self.assertEqual(sc.meters_per_unit, MPU[name])
    self.assertEqual(sc.name, name)
    g = sc.gaussians
    ids = np.asarray(sc.object_ids)
    self.assertEqual(ids.dtype, np.int32)
    self.assertEqual(ids.shape, (g.num,))
    counts = np.bincount(ids, minlength=sc.num_objects)
    self.assertEqual(len(counts), sc.num_objects)
    self.assertTrue(np.all(counts > 100), counts)
    for leaf in jax.tree.leaves(g):
      self.assertTrue(np.all(np.isfinite(np.asarray(leaf))))
    q = np.linalg.norm(np.asarray(g.quats), axis=-1)
    self.assertGreater(q.min(), 0.1)
    # Mesh-built Gaussians have unit quaternions (a captured PLY keeps its
    # raw ones).
    built = ~np.isin(ids, [i for i, o in enumerate(sc.objects)
                           if 'captured' in o.tags])
    np.testing.assert_allclose(q[built], 1.0, atol=_QUAT_TOL)
    self.assertEqual(g.sh_degree, 0)
    if name != 'donut':  # the captured donut is fixed at 45,624
      self.assertBetween(g.num, 3_000, 25_000)

  @parameterized.named_parameters(
    ('_tabletop', 'tabletop'), ('_ficus', 'ficus'), ('_donut', 'donut')
  )
  def test_cameras_look_at_the_scene(self, name):
    sc = _scene(name)
    self.assertLen(sc.cameras, NUM_CAMERAS)
    m = np.asarray(sc.gaussians.means)
    center = 0.5 * (m.min(0) + m.max(0))
    for cam in sc.cameras:
      (u, v), z = (np.asarray(x) for x in cam.project(center))
      self.assertGreater(z, 0.0)
      self.assertBetween(u, 0.2 * cam.width, 0.8 * cam.width)
      self.assertBetween(v, 0.2 * cam.height, 0.8 * cam.height)
      # OpenCV: world up (+z) points up in the image (camera -y).
      self.assertLess(np.asarray(cam.viewmat)[1, 2], 0.0)
      uv, depth = cam.project(m)
      uv = np.asarray(uv)
      inside = ((uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0)
                & (uv[:, 1] < cam.height) & (np.asarray(depth) > cam.near))
      self.assertGreater(inside.mean(), 0.9)

  def test_tabletop_objects_rest_on_the_table_apart(self):
    sc = _scene('tabletop')
    table = _part(sc, 'table top')
    top = table[:, 2].max()
    self.assertLess(abs(top), 1e-4)
    boxes = {}
    for o in sc.objects[1:]:
      m = _part(sc, o.name)
      gap = m[:, 2].min() - top
      self.assertBetween(gap, 0.0, _MAX_REST_GAP, msg=o.name)
      # Fully over the table.
      self.assertTrue(np.all(m[:, :2].min(0) > table[:, :2].min(0)), o.name)
      self.assertTrue(np.all(m[:, :2].max(0) < table[:, :2].max(0)), o.name)
      boxes[o.name] = (m[:, :2].min(0), m[:, :2].max(0))
    names = list(boxes)
    for i, a in enumerate(names):
      for b in names[i + 1:]:
        (alo, ahi), (blo, bhi) = boxes[a], boxes[b]
        sep = np.maximum(blo - ahi, alo - bhi).max()
        self.assertGreater(sep, 0.05, f'{a} and {b} are too close')

  def test_ficus_layout(self):
    sc = _scene('ficus')
    pot, soil = _part(sc, 'pot'), _part(sc, 'soil')
    stem, leaves = _part(sc, 'stem'), _part(sc, 'leaves')
    self.assertBetween(pot[:, 2].min(), 0.0, 0.003)
    soil_top = soil[:, 2].max()
    # Soil sits inside the pot, below the rim.
    self.assertLess(soil_top, pot[:, 2].max())
    self.assertLess(np.linalg.norm(soil[:, :2], axis=-1).max(),
                    np.linalg.norm(pot[:, :2], axis=-1).max())
    # The stem is rooted in the soil and the leaves are above it.
    self.assertLess(stem[:, 2].min(), soil_top)
    self.assertGreater(leaves[:, 2].min(), soil_top)
    self.assertGreater(leaves[:, 2].max(), 0.45)

  def test_donut_is_the_shipped_ply_on_a_board(self):
    sc = _scene('donut')
    ply = load_ply(donut_mod.DONUT_PLY)
    mask = np.asarray(sc.object_mask('donut'))
    self.assertEqual(int(mask.sum()), ply.num)
    board = int((~mask).sum())
    self.assertEqual(sc.gaussians.num, ply.num + board)
    np.testing.assert_array_equal(
      np.asarray(sc.gaussians.means)[mask], np.asarray(ply.means)
    )
    np.testing.assert_array_equal(
      np.asarray(sc.gaussians.sh)[mask], np.asarray(ply.sh)
    )
    donut, wood = _part(sc, 'donut'), _part(sc, 'wooden board')
    gap = donut[:, 2].min() - wood[:, 2].max()
    self.assertBetween(gap, 0.0, _MAX_REST_GAP)
    # Centred under the donut and wider than it.
    np.testing.assert_allclose(
      0.5 * (wood.min(0) + wood.max(0))[:2],
      0.5 * (donut.min(0) + donut.max(0))[:2], atol=0.005,
    )
    self.assertTrue(np.all(wood.max(0)[:2] > donut.max(0)[:2]))

  def test_donut_up_axis_is_z(self):
    # The icing (bluish) is on top, the bready side at the bottom.
    g = load_ply(donut_mod.DONUT_PLY)
    z = np.asarray(g.means)[:, 2]
    rgb = np.asarray(g.rgb_dc)
    top, bottom = rgb[z > 0.07].mean(0), rgb[z < 0.01].mean(0)
    self.assertGreater(top[2] - top[0], 0.3)  # blue > red on top
    self.assertGreater(bottom[0] - bottom[2], 0.1)  # warm at the bottom
    # Flat along z: the smallest principal axis is z.
    m = np.asarray(g.means)
    w, v = np.linalg.eigh(np.cov(m.T))
    self.assertGreater(abs(v[2, 0]), 0.95)

  def test_detail_knob(self):
    small = scenes.make_scene('tabletop', detail=0.5, num_cameras=0)
    self.assertLess(small.gaussians.num, 0.4 * _scene('tabletop').gaussians.num)


class SceneStoreTest(absltest.TestCase):
  """With a cache folder, a built scene is stored and read back as built."""

  def test_stored_scene_is_read_back_without_building(self):
    from unittest import mock  # noqa: PLC0415
    import os  # noqa: PLC0415
    import tempfile  # noqa: PLC0415
    from physsplat_jax import program_store  # noqa: PLC0415
    from physsplat_jax.scenes import registry  # noqa: PLC0415

    tmp = tempfile.TemporaryDirectory()
    self.addCleanup(tmp.cleanup)
    with mock.patch.object(program_store, 'folder', lambda: tmp.name):
      a = scenes.make_scene('tabletop', detail=0.4, num_cameras=2,
                            seed=jax.random.key(3))
      stored = os.listdir(os.path.join(tmp.name, registry.FOLDER))
      self.assertLen(stored, 1)
      with mock.patch.object(registry, '_builder',
                             side_effect=AssertionError('built again')):
        b = scenes.make_scene('tabletop', detail=0.4, num_cameras=2,
                              seed=jax.random.key(3))
      self.assertEqual(a.objects, b.objects)
      self.assertEqual((a.up_axis, a.name), (b.up_axis, b.name))
      self.assertLen(b.cameras, 2)
      self.assertEqual(b.cameras[1].width, a.cameras[1].width)
      for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        self.assertEqual(type(x), type(y))  # JAX arrays, as built
        np.testing.assert_array_equal(x, y)
        self.assertEqual(x.dtype, y.dtype)
      # Another option is another scene (built, stored beside it).
      c = scenes.make_scene('tabletop', detail=0.4, num_cameras=0,
                            seed=jax.random.key(3))
      self.assertEmpty(c.cameras)
      self.assertLen(os.listdir(os.path.join(tmp.name, registry.FOLDER)), 2)
      # An unreadable file is built again (and stored anew).
      path = os.path.join(tmp.name, registry.FOLDER, stored[0])
      with open(path, 'wb') as f:
        f.write(b'not a scene')
      with self.assertLogs(level='WARNING') as logs:
        d = scenes.make_scene('tabletop', detail=0.4, num_cameras=2,
                              seed=jax.random.key(3))
      self.assertIn('building the scene again', logs.output[0])
      np.testing.assert_array_equal(d.gaussians.means, a.gaussians.means)
      # Bytes changed in place, the length kept: read back with wrong
      # positions and no word before the file carried its digest.
      blob = bytearray(open(path, 'rb').read())
      blob[len(blob) // 2] ^= 0xFF
      with open(path, 'wb') as f:
        f.write(blob)
      with self.assertLogs(level='WARNING') as logs:
        e = scenes.make_scene('tabletop', detail=0.4, num_cameras=2,
                              seed=jax.random.key(3))
      self.assertIn('damaged', logs.output[0])
      self.assertIn(path, logs.output[0])
      np.testing.assert_array_equal(e.gaussians.means, a.gaussians.means)
      # An option that cannot name a file (an array of Gaussians) is not
      # stored; a bad option still names the options.
      self.assertIsNone(registry._stored_path('donut', {'donut': a.gaussians}))
      with self.assertRaisesRegex(TypeError, 'detail'):
        scenes.make_scene('tabletop', resolution=3)


class GaussiansFromMeshTest(parameterized.TestCase):

  def _check_surface(self, mesh, g, surf, normals_fn):
    m = np.asarray(g.means)
    _, dist, _ = trimesh.proximity.closest_point(mesh, m[surf])
    self.assertLess(dist.max(), 1e-5)
    R = np.asarray(g.rotations)
    scales = np.asarray(g.scales)
    # The shortest axis of every surface Gaussian is the normal.
    short = np.argmin(scales[surf], axis=-1)
    self.assertTrue(np.all(short == 2))
    n = R[surf][:, :, 2]
    cos = np.abs(np.sum(n * normals_fn(m[surf]), axis=-1))
    return cos

  def test_sphere(self):
    mesh = trimesh.creation.icosphere(4, 1.0)
    s = 0.08
    g, surf = gaussians_from_mesh(mesh, jax.random.key(0), surface_spacing=s,
                                  return_surface_mask=True)
    cos = self._check_surface(
      mesh, g, surf, lambda p: p / np.linalg.norm(p, axis=-1, keepdims=True)
    )
    self.assertGreater(cos.min(), 0.999)  # smoothed normals ~ radial
    np.testing.assert_allclose(surf.sum(), mesh.area / s**2, rtol=0.05)
    inner = np.asarray(g.means)[~surf]
    self.assertTrue(np.all(np.linalg.norm(inner, axis=-1) < 1.0))
    np.testing.assert_allclose(len(inner), mesh.volume / (1.5 * s) ** 3,
                               rtol=0.15)
    self.assertTrue(np.all(surf[: surf.sum()]))  # surface first

  def test_box_normals_and_colors(self):
    mesh = trimesh.creation.box((1.0, 2.0, 0.5))
    fc = np.zeros((len(mesh.faces), 3))
    fc[:, 0] = (mesh.face_normals[:, 2] > 0.5)  # red top, black elsewhere
    g, surf = gaussians_from_mesh(
      mesh, 3, surface_spacing=0.05, face_colors=fc, color_noise=0.0,
      shading=0.0, interior_shade=1.0, return_surface_mask=True,
    )

    def box_normal(p):
      d = np.abs(p) / np.array([0.5, 1.0, 0.25])
      n = np.zeros_like(p)
      a = np.argmax(d, axis=-1)
      n[np.arange(len(p)), a] = 1.0
      return n

    cos = self._check_surface(mesh, g, surf, box_normal)
    # Sharp edges stay sharp: the normal is the face's away from edges.
    self.assertGreater(np.median(cos), 0.9999)
    m = np.asarray(g.means)
    inner = m[~surf]
    self.assertTrue(np.all(mesh.contains(inner[::7])))
    rgb = np.asarray(g.rgb_dc)
    top = surf & (m[:, 2] > 0.25 - 1e-6)
    np.testing.assert_allclose(rgb[top], [[1.0, 0.0, 0.0]] * int(top.sum()),
                               atol=1e-5)
    side = surf & (np.abs(m[:, 2]) < 0.2)
    np.testing.assert_allclose(rgb[side], 0.0, atol=1e-5)

  def test_torus_interior_parity(self):
    # A non-convex solid: nothing may land in the hole.
    mesh = trimesh.creation.torus(1.0, 0.3)
    g, surf = gaussians_from_mesh(mesh, 0, surface_spacing=0.05,
                                  return_surface_mask=True)
    p = np.asarray(g.means)[~surf]
    self.assertGreater(np.linalg.norm(p[:, :2], axis=-1).min(), 0.65)
    self.assertTrue(np.all(mesh.contains(p[::5])))
    np.testing.assert_allclose(len(p), mesh.volume / 0.075**3, rtol=0.15)

  def test_vertex_and_function_colors(self):
    mesh = trimesh.creation.icosphere(2, 1.0)
    vc = np.where(mesh.vertices[:, :1] > 0, [0.0, 0.0, 1.0], [0.0, 1.0, 0.0])
    g = gaussians_from_mesh(mesh, 0, surface_spacing=0.1, vertex_colors=vc,
                            color_noise=0.0, shading=0.0, interior=False)
    rgb, m = np.asarray(g.rgb_dc), np.asarray(g.means)
    far = m[:, 0] > 0.5
    np.testing.assert_allclose(rgb[far], [[0, 0, 1]] * int(far.sum()),
                               atol=1e-5)
    fn = lambda p, n: np.where(n[:, 2:] > 0, [1.0, 1.0, 1.0], [0.2, 0.2, 0.2])
    g = gaussians_from_mesh(mesh, 0, surface_spacing=0.1, color=fn,
                            color_noise=0.0, shading=0.0, interior=False)
    rgb, m = np.asarray(g.rgb_dc), np.asarray(g.means)
    np.testing.assert_allclose(rgb[m[:, 2] > 0.2], 1.0, atol=1e-5)
    np.testing.assert_allclose(rgb[m[:, 2] < -0.2], 0.2, atol=1e-5)

  def test_deterministic_and_keyed(self):
    mesh = trimesh.creation.box((1.0, 1.0, 1.0))
    a = gaussians_from_mesh(mesh, jax.random.key(5), surface_spacing=0.1)
    b = gaussians_from_mesh(mesh, jax.random.key(5), surface_spacing=0.1)
    c = gaussians_from_mesh(mesh, jax.random.key(6), surface_spacing=0.1)
    d = gaussians_from_mesh(mesh, jax.random.PRNGKey(5), surface_spacing=0.1)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
      np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    self.assertFalse(np.array_equal(np.asarray(a.means), np.asarray(c.means))
                     and a.num == c.num)
    self.assertEqual(d.num > 0, True)

  def test_bad_inputs(self):
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    open_mesh = trimesh.Trimesh(box.vertices, box.faces[:-2])
    with self.assertRaisesRegex(MeshError, 'watertight'):
      gaussians_from_mesh(open_mesh, 0, surface_spacing=0.1)
    gaussians_from_mesh(open_mesh, 0, surface_spacing=0.1, interior=False)
    with self.assertRaisesRegex(MeshError, 'surface_spacing'):
      gaussians_from_mesh(box, 0, surface_spacing=0.0)
    with self.assertRaisesRegex(MeshError, 'max_gaussians'):
      gaussians_from_mesh(box, 0, surface_spacing=1e-4)
    with self.assertRaisesRegex(MeshError, r'\[0, 1\]'):
      gaussians_from_mesh(box, 0, surface_spacing=0.1, color=(2.0, 0, 0))
    with self.assertRaisesRegex(MeshError, 'face_colors'):
      gaussians_from_mesh(box, 0, surface_spacing=0.1,
                          face_colors=np.zeros((3, 3)))
    with self.assertRaisesRegex(MeshError, 'only one'):
      gaussians_from_mesh(box, 0, surface_spacing=0.1, color=(1, 0, 0),
                          face_colors=np.zeros((12, 3)))
    with self.assertRaisesRegex(MeshError, 'opacity'):
      gaussians_from_mesh(box, 0, surface_spacing=0.1, opacity=1.0)
    with self.assertRaisesRegex(MeshError, 'key'):
      gaussians_from_mesh(box, 'seed', surface_spacing=0.1)
    with self.assertRaisesRegex(MeshError, 'Trimesh'):
      gaussians_from_mesh(trimesh.Scene(), 0, surface_spacing=0.1)
    # Options that used to give -inf / NaN scales or colours silently.
    for name, value in (('thickness', 0.0), ('thickness', -0.1),
                        ('tangent_scale', 0.0), ('interior_scale', 0.0),
                        ('noise_scale', 0.0), ('scale_jitter', float('nan')),
                        ('color_noise', float('nan')),
                        ('light_dir', (0.0, 0.0, 0.0))):
      with self.subTest(name=name, value=value), \
          self.assertRaisesRegex(MeshError, name):
        gaussians_from_mesh(box, 0, surface_spacing=0.2, **{name: value})
    # No surface sample: an empty set (interior=False) or a KD-tree
    # IndexError (interior=True) before.
    for interior in (False, True):
      with self.subTest(interior=interior), \
          self.assertRaisesRegex(MeshError, 'no surface Gaussians'):
        gaussians_from_mesh(box, 0, surface_spacing=0.2, interior=interior,
                            face_mask=np.zeros(12, bool))


class BuildHelpersTest(absltest.TestCase):

  def test_tube_volume(self):
    n, r, length = 16, 0.1, 1.0
    tube = scenes.tube_mesh([[0, 0, 0], [0, 0, 0.5], [0, 0, length]], r, n)
    self.assertTrue(tube.is_watertight)
    polygon = 0.5 * n * r**2 * math.sin(2 * math.pi / n)
    np.testing.assert_allclose(tube.volume, polygon * length, rtol=1e-9)

  def test_tabletop_constants_consistent(self):
    # Layout footprints stay on the table with a margin.
    lx, ly, _ = tabletop_mod.TABLE_SIZE
    for name, (x, y) in tabletop_mod.LAYOUT.items():
      self.assertLess(abs(x) + 0.06, lx / 2, name)
      self.assertLess(abs(y) + 0.06, ly / 2, name)


if __name__ == '__main__':
  absltest.main()
