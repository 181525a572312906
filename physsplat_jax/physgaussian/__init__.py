"""PhysGaussian (Xie et al., CVPR 2024) scene configs and their driver.

``schema`` parses ``config/*.json`` into static dataclasses; ``transform``
maps them to arrays (materials, the normalised domain); ``driver`` runs a
config end to end (every selected Gaussian a particle, as PhysGaussian
does). This package sits above ``mpm`` and ``sampling`` and uses both; the
physics core never imports it.
"""

from physsplat_jax.mpm.models import CANONICAL_MODELS as CANONICAL_MODELS
from physsplat_jax.physgaussian.schema import BOUNDARY_TYPES as BOUNDARY_TYPES
from physsplat_jax.physgaussian.schema import SURFACE_TYPES as SURFACE_TYPES
from physsplat_jax.physgaussian.schema import PARTLY_HONOURED as PARTLY_HONOURED
from physsplat_jax.physgaussian.schema import NOT_HONOURED as NOT_HONOURED
from physsplat_jax.physgaussian.schema import ConfigError as ConfigError
from physsplat_jax.physgaussian.schema import MaterialBox as MaterialBox
from physsplat_jax.physgaussian.schema import (
  BoundaryCondition as BoundaryCondition)
from physsplat_jax.physgaussian.schema import ParticleFilling as ParticleFilling
from physsplat_jax.physgaussian.schema import CameraConfig as CameraConfig
from physsplat_jax.physgaussian.schema import (
  PhysGaussianConfig as PhysGaussianConfig)
from physsplat_jax.physgaussian.schema import MaterialParams as MaterialParams
from physsplat_jax.physgaussian.schema import NormTransform as NormTransform
from physsplat_jax.physgaussian.schema import material_name as material_name
from physsplat_jax.physgaussian.schema import parse_config as parse_config
from physsplat_jax.physgaussian.schema import load_config as load_config
from physsplat_jax.physgaussian.transform import (
  material_params as material_params)
from physsplat_jax.physgaussian.transform import (
  material_fields as material_fields)
from physsplat_jax.physgaussian.transform import (
  rotation_matrix as rotation_matrix)
from physsplat_jax.physgaussian.transform import (
  select_particles as select_particles)
from physsplat_jax.physgaussian.transform import (
  make_norm_transform as make_norm_transform)
from physsplat_jax.physgaussian.transform import (
  normalise_positions as normalise_positions)
from physsplat_jax.physgaussian.transform import (
  denormalise_positions as denormalise_positions)
from physsplat_jax.physgaussian.transform import (
  normalise_velocity as normalise_velocity)
from physsplat_jax.physgaussian.transform import (
  denormalise_velocity as denormalise_velocity)
from physsplat_jax.physgaussian.transform import cfl_substep as cfl_substep
from physsplat_jax.physgaussian.driver import PreparedSim as PreparedSim
from physsplat_jax.physgaussian.driver import grid_volumes as grid_volumes
from physsplat_jax.physgaussian.driver import (
  convert_boundary_conditions as convert_boundary_conditions)
from physsplat_jax.physgaussian.driver import make_sim_config as make_sim_config
from physsplat_jax.physgaussian.driver import transform_host as transform_host
from physsplat_jax.physgaussian.driver import fill_particles as fill_particles
from physsplat_jax.physgaussian.driver import prepare_config as prepare_config
from physsplat_jax.physgaussian.driver import simulate_config as simulate_config
from physsplat_jax.physgaussian.run import run_config as run_config
from physsplat_jax.physgaussian.segment import (
  segment_from_physgaussian as segment_from_physgaussian,
)
