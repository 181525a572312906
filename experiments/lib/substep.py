"""The static-config variants of a scene's MPM substep (what
``benchmark_substep`` times and ``gpu_kernels`` counts).

- ``scene``: the pipeline's config (materials grouped by model,
  ``SimConfig.model_counts``);
- ``split``: the same with one constitutive slice per model on every
  platform (on a GPU the scene's models with a spectral form otherwise
  share one blended slice, ``constitutive.constitutive_slices``: one
  kernel fewer, but one longer chain per particle);
- ``masked``: the same without ``model_counts`` (every model evaluated on
  every particle and selected, the rigid sums masked over all particles);
- ``no_plane``: the scene's config without the support plane;
- ``no_plane_no_body``: also without rigid bodies (their particles stay
  stress-free);
- ``bare``: every particle one fixed-corotated material, no body, no plane.
"""

import dataclasses
from unittest import mock

import jax
import jax.numpy as jnp
from absl import flags

from experiments.configs import demo as demo_config
from experiments.lib import cli
from experiments.lib import presets
from experiments.lib import simulate as lib
from physsplat_jax import mpm
from physsplat_jax import perception
from physsplat_jax import pipeline as pl
from physsplat_jax import scenes
from physsplat_jax.mpm import constitutive
from physsplat_jax.pipeline import simulation

VARIANTS = ('scene', 'split', 'masked', 'no_plane', 'no_plane_no_body',
            'bare')


def demo_scene_state(scene_name: str, preset: str = 'demo'):
  """A scene prepared with the `make demo` settings (experiments/configs/
  demo.py; or a benchmark preset, :func:`demo_scene`) and its initial MPM
  state.

  Returns:
    ``(prepared, state, materials, forces, sim_config)``.
  """
  config, prepared, params = demo_scene(scene_name, preset)
  state, mats, forces, sim_config = simulation.initial_state(
    params, prepared, config, field=prepared.field)
  return prepared, state, mats, forces, sim_config


PRESETS = ('demo',) + tuple(sorted(presets.PRESETS))


def define_preset() -> flags.FlagHolder:
  """``--preset`` (one of :data:`PRESETS`, default 'demo'), for the
  scripts that prepare a scene's substep (``benchmark_substep``,
  ``gpu_kernels``); the holder of the one already defined when both are
  imported into one process."""
  if 'preset' in flags.FLAGS:
    return flags.FlagHolder(flags.FLAGS, flags.FLAGS['preset'])
  return flags.DEFINE_enum(
    'preset', 'demo', PRESETS, 'settings the scene is prepared with: demo '
    '(the `make demo` ones) or a benchmark_pipeline preset (paper: 64^3, 768 '
    'substeps/frame at 30 fps, up to 200k particles)')


def demo_scene(scene_name: str, preset: str = 'demo'):
  """``(config, prepared, params)`` of a scene with the `make demo`
  settings (``preset='demo'``), or with a benchmark preset's
  (experiments/lib/presets.py: ``'paper'`` is what ``benchmark_pipeline
  --preset=paper`` simulates: experiments/configs/simulate.py's defaults
  and scene motions under the preset's fields)."""
  if preset == 'demo':
    config = lib.build_config(scene_name, demo_config.get_config(),
                              motions=demo_config.SCENE_MOTIONS)
  elif preset in presets.PRESETS:
    config = lib.build_config(scene_name, None,
                              overrides=presets.PRESETS[preset])
  else:
    raise cli.usage_error(f'--preset: unknown {preset!r}; use one of '
                          f'{", ".join(PRESETS)}')
  scene = scenes.load_scene(scene_name)
  materials = perception.perceive_scene(scene, None)
  prepared, _ = pl.prepare_scene(jax.random.PRNGKey(config.seed), scene,
                                 materials, config)
  return config, prepared, pl.init_params(prepared, config)


def variant(name, state, materials, forces, config):
  """The (state, materials, forces, config) of one variant."""
  if name not in VARIANTS:
    raise cli.usage_error(f'--variants: unknown variant {name!r}; use '
                          f'some of {", ".join(VARIANTS)}.')
  if name in ('masked', 'bare'):
    config = dataclasses.replace(config, model_counts=None)
  if name in ('no_plane', 'no_plane_no_body', 'bare'):
    keep = [i for i, bc in enumerate(config.boundary_conditions)
            if not isinstance(bc, mpm.SurfaceCollider)]
    # Particle conditions keep their per-particle data (bc_data follows
    # config.particle_bcs, whose order does not change).
    config = dataclasses.replace(config, boundary_conditions=tuple(
      config.boundary_conditions[i] for i in keep))
    forces = mpm.Forces(values=tuple(forces.values[i] for i in keep))
  if name in ('no_plane_no_body', 'bare'):
    # The rigid particles stay stress-free ('rigid' model), without a body.
    config = dataclasses.replace(config, num_bodies=0, body_fixed=())
    state = state.replace(body_id=-jnp.ones_like(state.body_id))
  if name == 'bare':
    config = dataclasses.replace(config, models=('fixed_corotated',))
    materials = materials.replace(
      model_id=jnp.zeros_like(materials.model_id))
  return state, materials, forces, config


def make_frame(name, config):
  """``mpm.make_frame(config)`` for variant ``name`` (``split``: built
  with every platform's constitutive slices one per model)."""
  if name != 'split':
    return mpm.make_frame(config)
  per_model = constitutive.constitutive_slices
  with mock.patch.object(constitutive, 'constitutive_slices',
                         lambda c, merge: per_model(c, merge=False)):
    return mpm.make_frame(config)
