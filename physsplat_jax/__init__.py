"""physsplat_jax: PhysSplat (ICCV 2025) in pure JAX.

Turns a static 3D Gaussian Splatting scene into a physically simulated one
(MLS-MPM) and renders it, differentiably, on CPU and GPU::

  import jax
  import physsplat_jax as ps

  scene = ps.load_scene('tabletop')                 # built-in name or PLY
  materials = ps.perceive_scene(scene)              # MLLM-P3 or library
  config = ps.PipelineConfig(num_frames=30)
  prepared, report = ps.prepare_scene(jax.random.PRNGKey(0), scene,
                                      materials, config)
  params = ps.init_params(prepared, config)
  traj = ps.simulate_jit(params, prepared, config)  # pure, differentiable
  ps.run(params, prepared, config, out_dir='out')   # video, PNG, PLY

This file is the public API, listed once. Subpackages, in the order the
data flows (imports run one way, down this list):

- core: ``types``, ``gaussians``, ``cameras``, ``sh_rotation``;
- pure kernels and models: ``mpm``, ``render``, ``sampling``, ``deform``,
  ``mpdp``;
- ``io`` (files only), ``scenes``, ``segmentation``, ``perception``,
  ``physgaussian`` (the PhysGaussian JSON format and its driver);
- ``pipeline`` (config, prepare, simulate, host loop, whole-scene job);
- ``training`` (MPDP training and material fitting through the
  simulator), ``distributed`` (sweeps and sharded simulations).
"""

import importlib as _importlib
import warnings as _warnings

from physsplat_jax import platforms as _platforms

# XLA:CPU's setting for the solver's reductions (platforms.tune_xla_cpu:
# before JAX's first computation; PHYSSPLAT_JAX_XLA_CPU_TUNING=0 opts out).
_platforms.tune_xla_cpu()

# Subpackages, reachable by their names (ps.render.project, ps.mpm.rollout).
from physsplat_jax import cameras as cameras
from physsplat_jax import deform as deform
from physsplat_jax import gaussians as gaussians
from physsplat_jax import io as io
from physsplat_jax import mpdp as mpdp
from physsplat_jax import mpm as mpm
from physsplat_jax import perception as perception
from physsplat_jax import physgaussian as physgaussian
from physsplat_jax import pipeline as pipeline
from physsplat_jax import render as render
from physsplat_jax import sampling as sampling
from physsplat_jax import scenes as scenes
from physsplat_jax import segmentation as segmentation
from physsplat_jax import types as types

# Compile once: the persistent compilation cache.
from physsplat_jax.compile_cache import (
  enable_compilation_cache as enable_compilation_cache,
)

# Core types and Gaussian maths.
from physsplat_jax.gaussians import covariance as covariance
from physsplat_jax.gaussians import decompose_covariance as decompose_covariance
from physsplat_jax.gaussians import eval_sh as eval_sh
from physsplat_jax.gaussians import quat_to_rotmat as quat_to_rotmat
from physsplat_jax.gaussians import rotmat_to_quat as rotmat_to_quat
from physsplat_jax.types import Camera as Camera
from physsplat_jax.types import Gaussians as Gaussians
from physsplat_jax.types import ObjectInfo as ObjectInfo
from physsplat_jax.types import Scene as Scene
from physsplat_jax.types import concatenate_gaussians as concatenate_gaussians
from physsplat_jax.types import make_camera as make_camera

# Scenes in and out.
from physsplat_jax.io.cameras import load_cameras as load_cameras
from physsplat_jax.io.export import DeformedFrameWriter as DeformedFrameWriter
from physsplat_jax.io.export import save_deformed_ply as save_deformed_ply
from physsplat_jax.io.export import save_deformed_splat as save_deformed_splat
from physsplat_jax.io.ply import PlyError as PlyError
from physsplat_jax.io.scene import SceneFileError as SceneFileError
from physsplat_jax.io.scene import save_scene as save_scene
from physsplat_jax.io.splat import load_splat as load_splat
from physsplat_jax.io.splat import save_splat as save_splat
from physsplat_jax.io.spz import load_spz as load_spz
from physsplat_jax.io.spz import save_spz as save_spz
from physsplat_jax.io.video import VideoWriter as VideoWriter
from physsplat_jax.io.video import write_png_frames as write_png_frames
from physsplat_jax.io.video import write_video as write_video
from physsplat_jax.scenes import list_scenes as list_scenes
from physsplat_jax.scenes import load_scene as load_scene
from physsplat_jax.scenes import make_scene as make_scene

# Segmentation and material perception.
from physsplat_jax.io.mllm import MLLMConfig as MLLMConfig
from physsplat_jax.perception import MaterialChoice as MaterialChoice
from physsplat_jax.perception import MaterialLibrary as MaterialLibrary
from physsplat_jax.perception import ObjectMaterial as ObjectMaterial
from physsplat_jax.perception import PerceptionOptions as PerceptionOptions
from physsplat_jax.perception import default_library as default_library
from physsplat_jax.perception import perceive_scene as perceive_scene
from physsplat_jax.segmentation import Segmentation as Segmentation
from physsplat_jax.segmentation import fill_support_hole as fill_support_hole
from physsplat_jax.segmentation import segment as segment

# Rendering (``ps.render`` is the subpackage; ``ps.render.render`` renders).
from physsplat_jax.render import RenderConfig as RenderConfig
from physsplat_jax.render import RenderOutput as RenderOutput
from physsplat_jax.render import fit_render_config as fit_render_config
from physsplat_jax.render import render_differentiable as render_differentiable
from physsplat_jax.render import render_image as render_image
from physsplat_jax.render import render_scene as render_scene
from physsplat_jax.render import space_time_slice as space_time_slice

# Simulation.
from physsplat_jax.mpm import SimulationError as SimulationError
from physsplat_jax.pipeline import CameraPath as CameraPath
from physsplat_jax.pipeline import ForceKind as ForceKind
from physsplat_jax.pipeline import ForceSpec as ForceSpec
from physsplat_jax.pipeline import Ground as Ground
from physsplat_jax.pipeline import Params as Params
from physsplat_jax.pipeline import PipelineConfig as PipelineConfig
from physsplat_jax.pipeline import PipelineError as PipelineError
from physsplat_jax.pipeline import PrepareConfig as PrepareConfig
from physsplat_jax.pipeline import PreparedScene as PreparedScene
from physsplat_jax.pipeline import RenderMode as RenderMode
from physsplat_jax.pipeline import RunOutput as RunOutput
from physsplat_jax.pipeline import Sampling as Sampling
from physsplat_jax.pipeline import SimulateConfig as SimulateConfig
from physsplat_jax.pipeline import Trajectory as Trajectory
from physsplat_jax.pipeline import init_params as init_params
from physsplat_jax.pipeline import prepare_scene as prepare_scene
from physsplat_jax.pipeline import run as run
from physsplat_jax.pipeline import simulate as simulate
from physsplat_jax.pipeline import simulate_jit as simulate_jit
from physsplat_jax.pipeline import simulate_scene as simulate_scene

# Imported at first use (``ps.training``, ``ps.sweep_params``, ...): they
# bring optax and orbax, which a simulation does not need (on a GPU host of
# 2026-11-27 importing them was over a second of a run's start).
# ``training``: MPDP training and material fitting through the simulator;
# ``distributed``, and from it the scale-out functions: sweeps and large
# simulations over many devices and hosts.
_LAZY = {
  'training': ('physsplat_jax.training', None),
  'distributed': ('physsplat_jax.distributed', None),
  'make_simulate_batch': ('physsplat_jax.distributed', 'make_simulate_batch'),
  'simulate_sharded': ('physsplat_jax.distributed', 'simulate_sharded'),
  'sweep_params': ('physsplat_jax.distributed', 'sweep_params'),
  # trimesh, imported when a mesh is converted or a scene built.
  'gaussians_from_mesh': ('physsplat_jax.scenes.mesh', 'gaussians_from_mesh'),
}

__version__ = '0.2.0'

# Old top-level names kept for one release (each warns where it is used).
_DEPRECATED = {
  'load_ply': ('physsplat_jax.io.ply', 'load_ply',
               'ps.io.load_ply (Gaussians) or ps.load_scene (a Scene)'),
  'save_ply': ('physsplat_jax.io.ply', 'save_ply',
               'ps.io.save_ply (Gaussians) or ps.save_scene (a Scene)'),
}


def __getattr__(name):
  if name in _LAZY:
    module, attr = _LAZY[name]
    value = _importlib.import_module(module)
    if attr is not None:
      value = getattr(value, attr)
    globals()[name] = value  # once
    return value
  if name in _DEPRECATED:
    module, attr, instead = _DEPRECATED[name]
    _warnings.warn(f'physsplat_jax.{name} is deprecated: use {instead}; it '
                   'goes in the next release.', DeprecationWarning,
                   stacklevel=2)
    return getattr(_importlib.import_module(module), attr)
  raise AttributeError(f'module {__name__!r} has no attribute {name!r}')


def __dir__():
  return sorted(set(globals()) | set(_LAZY))
