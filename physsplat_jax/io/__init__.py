"""File I/O: 3DGS scenes (PLY, compressed PLY, .splat) and camera files.

The filesystem is touched only here (and in ``experiments/``). Render outputs
(video, frames) live in ``io.video`` and ``io.frames``; import them from there.
"""

from physsplat_jax.io.cameras import CameraFileError as CameraFileError
from physsplat_jax.io.cameras import load_cameras as load_cameras
from physsplat_jax.io.cameras import load_inria_cameras as load_inria_cameras
from physsplat_jax.io.cameras import (
  load_transforms_cameras as load_transforms_cameras,
)
from physsplat_jax.io.cameras import save_inria_cameras as save_inria_cameras
from physsplat_jax.io.ply import PlyError as PlyError
from physsplat_jax.io.ply import load_ply as load_ply
from physsplat_jax.io.ply import read_ply as read_ply
from physsplat_jax.io.ply import read_ply_header as read_ply_header
from physsplat_jax.io.ply import save_compressed_ply as save_compressed_ply
from physsplat_jax.io.ply import save_ply as save_ply
from physsplat_jax.io.ply import write_ply as write_ply
from physsplat_jax.io.splat import SplatError as SplatError
from physsplat_jax.io.splat import load_splat as load_splat
from physsplat_jax.io.splat import save_splat as save_splat
