"""``physsplat_jax.struct``: frozen pytree dataclasses (flax.struct's API)."""

import dataclasses

from absl.testing import absltest
import jax
import jax.numpy as jnp
import numpy as np

from physsplat_jax import struct


class Point(struct.PyTreeNode):
  x: jax.Array
  v: jax.Array
  res: int = struct.field(pytree_node=False, default=4)
  tags: dict = struct.field(default_factory=dict)


class Labelled(Point):
  name: str = struct.field(pytree_node=False, default='')


class StructTest(absltest.TestCase):

  def test_leaves_static_fields_and_replace(self):
    p = Point(jnp.ones(3), jnp.zeros(3), res=8)
    leaves, tree = jax.tree.flatten(p)
    self.assertLen(leaves, 2)  # x, v (the empty dict has no leaves)
    q = jax.tree.unflatten(tree, [a + 1 for a in leaves])
    np.testing.assert_array_equal(q.x, 2 * np.ones(3))
    self.assertEqual(q.res, 8)
    r = p.replace(res=16)
    self.assertEqual((p.res, r.res), (8, 16))
    self.assertNotEqual(jax.tree.structure(r), tree)  # static: new tree
    with self.assertRaises(dataclasses.FrozenInstanceError):
      p.res = 3

  def test_jit_grad_and_key_paths(self):
    p = Point(jnp.arange(3.0), jnp.ones(3), tags={'w': jnp.array(2.0)})

    @jax.jit
    def energy(p):
      return jnp.sum(p.x ** 2 * p.tags['w']) * p.res + jnp.sum(p.v)

    g = jax.grad(energy)(p)
    self.assertIsInstance(g, Point)
    np.testing.assert_allclose(g.x, 2 * np.arange(3.0) * 2.0 * 4)
    np.testing.assert_allclose(g.tags['w'], 5.0 * 4)
    paths = [jax.tree_util.keystr(k)
             for k, _ in jax.tree_util.tree_flatten_with_path(p)[0]]
    self.assertEqual(paths, ['.x', '.v', ".tags['w']"])

  def test_subclass_adds_its_fields(self):
    p = Labelled(jnp.ones(2), jnp.ones(2), name='a')
    self.assertEqual(p.replace(name='b').name, 'b')
    self.assertLen(jax.tree.leaves(p), 2)
    self.assertNotEqual(jax.tree.structure(p),
                        jax.tree.structure(p.replace(name='b')))


if __name__ == '__main__':
  absltest.main()
