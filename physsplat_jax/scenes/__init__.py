"""Built-in scenes made from meshes, and the mesh -> Gaussians converter.

``make_scene(name, **options)`` builds one of :func:`list_scenes`:

* ``tabletop`` (the default demo scene): jelly cube, rubber ball, sand pile
  and metal can on a wooden table top;
* ``ficus``: a potted plant (terracotta pot, soil, stem, leaves);
* ``donut``: the real captured donut (shipped PLY) on a wooden board.

See docs/scenes.md for sizes, materials and pictures.
"""

from physsplat_jax.scenes.registry import DEFAULT_SCENE as DEFAULT_SCENE
from physsplat_jax.scenes.registry import list_scenes as list_scenes
from physsplat_jax.scenes.registry import load_scene as load_scene
from physsplat_jax.scenes.registry import make_scene as make_scene
from physsplat_jax.scenes.registry import scene_options as scene_options

import importlib as _importlib

# The mesh tools import trimesh (0.1 s): loaded on first use, so that a run
# whose built-in scene is read back from the scene store never imports it.
_LAZY = {
  'assemble_scene': 'physsplat_jax.scenes.build',
  'orbit_rig': 'physsplat_jax.scenes.build',
  'tube_mesh': 'physsplat_jax.scenes.build',
  'MeshError': 'physsplat_jax.scenes.mesh',
  'gaussians_from_mesh': 'physsplat_jax.scenes.mesh',
  'interior_lattice': 'physsplat_jax.scenes.mesh',
}


def __getattr__(name):
  if name in _LAZY:
    value = getattr(_importlib.import_module(_LAZY[name]), name)
    globals()[name] = value
    return value
  raise AttributeError(f'module {__name__!r} has no attribute {name!r}')


def __dir__():
  return sorted(set(globals()) | set(_LAZY))
