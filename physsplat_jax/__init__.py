"""physsplat_jax: PhysSplat (ICCV 2025) in pure JAX.

Turns a static 3D Gaussian Splatting scene into a physically simulated one
(MLS-MPM) and renders it, differentiably, on CPU and GPU.

The public API is re-exported here; import from ``physsplat_jax`` rather than
from submodules.
"""

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

__version__ = '0.1.0'
