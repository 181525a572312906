"""Built-in scenes made from meshes, and the mesh -> Gaussians converter.

``make_scene(name, **options)`` builds one of :func:`list_scenes`:

* ``tabletop`` (the default demo scene): jelly cube, rubber ball, sand pile
  and metal can on a wooden table top;
* ``ficus``: a potted plant (terracotta pot, soil, stem, leaves);
* ``donut``: the real captured donut (shipped PLY) on a wooden board.

See docs/scenes.md for sizes, materials and pictures.
"""

from physsplat_jax.scenes.build import assemble_scene as assemble_scene
from physsplat_jax.scenes.build import orbit_rig as orbit_rig
from physsplat_jax.scenes.build import tube_mesh as tube_mesh
from physsplat_jax.scenes.mesh import MeshError as MeshError
from physsplat_jax.scenes.mesh import gaussians_from_mesh as gaussians_from_mesh
from physsplat_jax.scenes.mesh import interior_lattice as interior_lattice
from physsplat_jax.scenes.registry import DEFAULT_SCENE as DEFAULT_SCENE
from physsplat_jax.scenes.registry import list_scenes as list_scenes
from physsplat_jax.scenes.registry import load_scene as load_scene
from physsplat_jax.scenes.registry import make_scene as make_scene
from physsplat_jax.scenes.registry import scene_options as scene_options
