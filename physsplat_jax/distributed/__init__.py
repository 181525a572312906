"""Scale-out: many devices and hosts (see docs/distributed.md).

- runtime: ``initialize`` / ``define_flags`` / ``initialize_from_flags``
  start ``jax.distributed`` (explicit flags, or auto-detected under Slurm,
  Open MPI and TPU) before any JAX computation;
- batches sharded over devices: ``make_mesh``, ``put``, ``to_host``,
  ``stack_trees``, ``sharded_vmap`` (parameter sweeps, scene batches) and
  ``sharded_value_and_grad`` (mean loss of a sharded training batch);
- one large simulation across devices: ``rollout_sharded`` and
  ``simulate_sharded`` (particles sharded, P2G grid summed with
  ``lax.psum``, grid update replicated, G2P local);
- sweeps of the pipeline: ``make_simulate_batch``, ``sweep_params``.
"""

from physsplat_jax.distributed.particles import GHOST_FRACTION as GHOST_FRACTION
from physsplat_jax.distributed.particles import pad_particles as pad_particles
from physsplat_jax.distributed.particles import (
  rollout_sharded as rollout_sharded)
from physsplat_jax.distributed.particles import (
  simulate_sharded as simulate_sharded)
from physsplat_jax.distributed.particles import (
  simulate_sharded_jit as simulate_sharded_jit)
from physsplat_jax.distributed.runtime import (
  DistributedError as DistributedError)
from physsplat_jax.distributed.runtime import (
  DistributedStartError as DistributedStartError)
from physsplat_jax.distributed.runtime import RuntimeInfo as RuntimeInfo
from physsplat_jax.distributed.runtime import (
  cluster_environment as cluster_environment)
from physsplat_jax.distributed.runtime import define_flags as define_flags
from physsplat_jax.distributed.runtime import initialize as initialize
from physsplat_jax.distributed.runtime import (
  initialize_from_flags as initialize_from_flags)
from physsplat_jax.distributed.sharding import BATCH_AXIS as BATCH_AXIS
from physsplat_jax.distributed.sharding import PARTICLE_AXIS as PARTICLE_AXIS
from physsplat_jax.distributed.sharding import batch_sharding as batch_sharding
from physsplat_jax.distributed.sharding import make_mesh as make_mesh
from physsplat_jax.distributed.sharding import put as put
from physsplat_jax.distributed.sharding import replicated as replicated
from physsplat_jax.distributed.sharding import (
  sharded_value_and_grad as sharded_value_and_grad)
from physsplat_jax.distributed.sharding import sharded_vmap as sharded_vmap
from physsplat_jax.distributed.sharding import stack_trees as stack_trees
from physsplat_jax.distributed.sharding import to_host as to_host
from physsplat_jax.distributed.sweep import PARAMS_AXES as PARAMS_AXES
from physsplat_jax.distributed.sweep import (
  make_simulate_batch as make_simulate_batch)
from physsplat_jax.distributed.sweep import sweep_params as sweep_params
