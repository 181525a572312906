"""The package layout: imports run one way, modules stay readable.

Layers, bottom to top (README, "Package layout"): core -> pure kernels and
models -> files, scenes, objects, materials -> pipeline -> training and
distributed. Every import in the package (module level or inside a
function) is parsed from the source and checked against the layer rules.
"""

import ast
import pathlib

from absl.testing import absltest

ROOT = pathlib.Path(__file__).resolve().parent.parent / 'physsplat_jax'

CORE = {'types', 'struct', 'gaussians', 'cameras', 'sh_rotation', 'errors',
        'compile_cache', 'program_store', 'sorting', 'test_util', 'values',
        'platforms', 'atomic_files'}
LAYER = {
  **{m: 0 for m in CORE},
  **{m: 1 for m in ('mpm', 'render', 'sampling', 'deform', 'mpdp')},
  **{m: 2 for m in ('io', 'scenes', 'segmentation', 'perception',
                    'physgaussian')},
  'pipeline': 3,
  'training': 4, 'distributed': 4,
}
# Within a layer, who may import whom (anything not listed: no sideways
# imports). io is files only: it sees the core and nothing else.
SIDEWAYS = {
  'mpdp': {'mpm'},  # model names only (mpm.models)
  'scenes': {'io'},
  'segmentation': {'io'},
  'perception': {'io', 'segmentation'},
  'physgaussian': {'io', 'segmentation'},
}
MAX_MODULE_LINES = 800


def _top(module: str) -> str | None:
  parts = module.split('.')
  if parts[0] != 'physsplat_jax' or len(parts) < 2:
    return None
  return parts[1]


def _imports(path: pathlib.Path) -> list[str]:
  tree = ast.parse(path.read_text())
  out = []
  for node in ast.walk(tree):
    if isinstance(node, ast.Import):
      out += [a.name for a in node.names]
    elif isinstance(node, ast.ImportFrom) and node.module:
      if node.module == 'physsplat_jax':
        out += [f'physsplat_jax.{a.name}' for a in node.names]
      else:
        out.append(node.module)
  return out


def _package_of(path: pathlib.Path) -> str:
  rel = path.relative_to(ROOT).parts
  return rel[0][:-3] if len(rel) == 1 else rel[0]


class LayoutTest(absltest.TestCase):

  def test_every_module_has_a_layer(self):
    for path in ROOT.rglob('*.py'):
      if path.parent == ROOT and path.name == '__init__.py':
        continue
      self.assertIn(_package_of(path), LAYER, msg=str(path))

  def test_imports_run_one_way(self):
    bad = []
    for path in ROOT.rglob('*.py'):
      if path.parent == ROOT and path.name == '__init__.py':
        continue  # the public API re-exports every layer
      me = _package_of(path)
      for imp in _imports(path):
        dep = _top(imp)
        if dep is None or dep == me:
          continue
        if dep not in LAYER:
          bad.append(f'{path.relative_to(ROOT)} imports unknown {imp}')
        elif LAYER[dep] > LAYER[me]:
          bad.append(f'{path.relative_to(ROOT)} imports {imp} (layer '
                     f'{LAYER[dep]} above {LAYER[me]})')
        elif LAYER[dep] == LAYER[me] and LAYER[me] > 0 and (
            dep not in SIDEWAYS.get(me, set())):
          bad.append(f'{path.relative_to(ROOT)} imports {imp} (sideways)')
    self.assertEqual(bad, [])

  def test_no_module_over_the_limit(self):
    long = {str(p.relative_to(ROOT)): n for p in ROOT.rglob('*.py')
            if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
    self.assertEqual(long, {})

  def test_subpackages_reachable_by_name(self):
    import physsplat_jax as ps

    self.assertTrue(callable(ps.render.project))
    self.assertTrue(callable(ps.render.render))
    self.assertTrue(callable(ps.mpm.rollout))
    self.assertTrue(callable(ps.pipeline.simulate))
    self.assertTrue(callable(ps.physgaussian.parse_config))
    self.assertTrue(callable(ps.training.fit_material))

  def test_old_names_warn(self):
    import physsplat_jax as ps

    with self.assertWarns(DeprecationWarning):
      self.assertIs(ps.load_ply, ps.io.load_ply)
    with self.assertWarns(DeprecationWarning):
      self.assertIs(ps.save_ply, ps.io.save_ply)

  def test_flat_config_is_exactly_its_two_parts(self):
    import dataclasses

    from physsplat_jax import pipeline as pl

    def defaults(cls):
      return {f.name: f.default for f in dataclasses.fields(cls)}

    flat = defaults(pl.PipelineConfig)
    parts = {**defaults(pl.PrepareConfig), **defaults(pl.SimulateConfig)}
    self.assertEqual(set(flat) - set(parts), {'seed'})
    for name, value in parts.items():
      self.assertEqual(flat[name], value, msg=name)

  def test_one_material_record_and_attribute_list(self):
    import physsplat_jax as ps
    from physsplat_jax.io import scene as scene_io
    from physsplat_jax.segmentation import attributes

    self.assertIs(ps.ObjectMaterial, ps.MaterialChoice)
    self.assertIs(attributes.ATTRIBUTE_KEYS, scene_io.ID_PROPERTIES)
    self.assertIs(ps.mpdp.MODEL_NAMES, ps.mpm.CANONICAL_MODELS)


if __name__ == '__main__':
  absltest.main()
