"""The pipeline: ``prepare_scene`` (host, discrete) and ``simulate`` (pure).

PhysSplat (ICCV 2025) end to end::

  scene = segment_stage(scene, method)                   # objects
  materials = perception.perceive_scene(scene)           # MLLM-P3 / library
  prepared, report = prepare_scene(key, scene, materials, config.prepare)
  params = init_params(prepared, config)                 # differentiable
  traj = simulate(params, prepared, config.simulate)     # pure, jit-able
  out = run(params, prepared, config.simulate, out_dir=...)   # host loop

Modules, in the order the data flows: ``config`` (settings: host-side
:class:`PrepareConfig`, static :class:`SimulateConfig`, both in
:class:`PipelineConfig`), ``frames`` (scene <-> simulation frame, camera),
``colliders`` (fixed objects as boundary conditions), ``prepare`` (named
host stages), ``simulation`` (the pure ``simulate``), ``host`` (the one host
loop with pluggable writers from :mod:`physsplat_jax.io.outputs`) and ``job``
(segment -> perceive -> prepare -> run -> report for one scene).
"""

from physsplat_jax.pipeline.colliders import Colliders as Colliders
from physsplat_jax.pipeline.colliders import find_colliders as find_colliders
from physsplat_jax.pipeline.config import CameraPath as CameraPath
from physsplat_jax.pipeline.config import ForceKind as ForceKind
from physsplat_jax.pipeline.config import ForceSpec as ForceSpec
from physsplat_jax.pipeline.config import Ground as Ground
from physsplat_jax.pipeline.config import PipelineConfig as PipelineConfig
from physsplat_jax.pipeline.config import PipelineError as PipelineError
from physsplat_jax.pipeline.config import PrepareConfig as PrepareConfig
from physsplat_jax.pipeline.config import RenderMode as RenderMode
from physsplat_jax.pipeline.config import Sampling as Sampling
from physsplat_jax.pipeline.config import SimulateConfig as SimulateConfig
from physsplat_jax.pipeline.config import config_from_dict as config_from_dict
from physsplat_jax.pipeline.frames import SimFrame as SimFrame
from physsplat_jax.pipeline.frames import render_camera as render_camera
from physsplat_jax.pipeline.frames import (
  transform_gaussians as transform_gaussians,
)
from physsplat_jax.pipeline.frames import up_rotation as up_rotation
from physsplat_jax.pipeline.host import RunOutput as RunOutput
from physsplat_jax.pipeline.host import default_writers as default_writers
from physsplat_jax.pipeline.host import run as run
from physsplat_jax.pipeline.host import save_trajectory as save_trajectory
from physsplat_jax.pipeline.job import segment_stage as segment_stage
from physsplat_jax.pipeline.job import select_objects as select_objects
from physsplat_jax.pipeline.job import simulate_scene as simulate_scene
from physsplat_jax.pipeline.job import summary as summary
from physsplat_jax.pipeline.prepare import Params as Params
from physsplat_jax.pipeline.prepare import PrepareReport as PrepareReport
from physsplat_jax.pipeline.prepare import PreparedScene as PreparedScene
from physsplat_jax.pipeline.prepare import SimSpec as SimSpec
from physsplat_jax.pipeline.prepare import prepare_scene as prepare_scene
from physsplat_jax.pipeline.simulation import Trajectory as Trajectory
from physsplat_jax.pipeline.simulation import assemble_scene as assemble_scene
from physsplat_jax.pipeline.simulation import check_finite as check_finite
from physsplat_jax.pipeline.simulation import (
  deformed_gaussians as deformed_gaussians,
)
from physsplat_jax.pipeline.simulation import (
  driver_materials as driver_materials,
)
from physsplat_jax.pipeline.simulation import init_params as init_params
from physsplat_jax.pipeline.simulation import initial_state as initial_state
from physsplat_jax.pipeline.simulation import make_sim_config as make_sim_config
from physsplat_jax.pipeline.simulation import render_frame as render_frame
from physsplat_jax.pipeline.simulation import simulate as simulate
from physsplat_jax.pipeline.simulation import simulate_jit as simulate_jit
from physsplat_jax.perception.choice import ObjectMaterial as ObjectMaterial
