"""MLS-MPM simulation core (Hu et al. 2018), pure JAX and differentiable.

Public API (see docs/mpm.md):

- configuration: ``GridSpec``, ``SimConfig`` and the boundary conditions
  ``SurfaceCollider``, ``Cuboid``, ``ParticleImpulse``, ``PointForce``,
  ``EnforceTranslation``, ``EnforceRotation``, ``SequentialRelease``;
- differentiable inputs: ``Materials`` / ``make_materials``, ``Forces`` /
  ``make_forces``;
- state: ``MPMState`` / ``init_state``;
- stepping: ``make_substep``, ``make_frame``, ``rollout`` (jit/grad) and
  ``run`` (host loop with checks) -> ``RunResult``, ``FrameLoop`` (the same
  loop as an iterator, optionally one frame ahead);
- time step: ``cfl_dt``, ``stable_dt``, ``choose_substeps``, ``check_dt``;
- errors: ``SimulationError``.
"""

from physsplat_jax.mpm.base import CANONICAL_MODELS as CANONICAL_MODELS
from physsplat_jax.mpm.base import CONSTITUTIVE_KERNELS as CONSTITUTIVE_KERNELS
from physsplat_jax.mpm.base import GPU_GRAPHS as GPU_GRAPHS
from physsplat_jax.mpm.base import FLOAT_FIELDS as FLOAT_FIELDS
from physsplat_jax.mpm.base import Cuboid as Cuboid
from physsplat_jax.mpm.base import EnforceRotation as EnforceRotation
from physsplat_jax.mpm.base import EnforceTranslation as EnforceTranslation
from physsplat_jax.mpm.base import Forces as Forces
from physsplat_jax.mpm.base import GridSpec as GridSpec
from physsplat_jax.mpm.base import MODEL_DEFAULTS as MODEL_DEFAULTS
from physsplat_jax.mpm.base import MPMInputError as MPMInputError
from physsplat_jax.mpm.base import MPMState as MPMState
from physsplat_jax.mpm.base import Materials as Materials
from physsplat_jax.mpm.base import ParticleImpulse as ParticleImpulse
from physsplat_jax.mpm.base import PointForce as PointForce
from physsplat_jax.mpm.base import SequentialRelease as SequentialRelease
from physsplat_jax.mpm.base import SimConfig as SimConfig
from physsplat_jax.mpm.base import SimulationError as SimulationError
from physsplat_jax.mpm.base import SurfaceCollider as SurfaceCollider
from physsplat_jax.mpm.base import lame as lame
from physsplat_jax.mpm.base import make_forces as make_forces
from physsplat_jax.mpm.base import make_materials as make_materials
from physsplat_jax.mpm.base import model_default as model_default
from physsplat_jax.mpm.solver import FrameLoop as FrameLoop
from physsplat_jax.mpm.solver import RunResult as RunResult
from physsplat_jax.mpm.solver import init_state as init_state
from physsplat_jax.mpm.solver import make_frame as make_frame
from physsplat_jax.mpm.solver import make_substep as make_substep
from physsplat_jax.mpm.solver import split_fix as split_fix
from physsplat_jax.mpm.solver import rollout as rollout
from physsplat_jax.mpm.solver import run as run
from physsplat_jax.mpm.timestep import cfl_dt as cfl_dt
from physsplat_jax.mpm.timestep import check_dt as check_dt
from physsplat_jax.mpm.timestep import choose_substeps as choose_substeps
from physsplat_jax.mpm.timestep import stable_dt as stable_dt
