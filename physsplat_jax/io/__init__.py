"""File I/O: 3DGS scenes (PLY, compressed PLY, .splat, .spz) and cameras.

The filesystem is touched only here (and in ``experiments/``). Outputs live
in ``io.video`` (MP4/GIF/PNG, space-time slices), ``io.export`` (deformed
Gaussians as per-frame PLY / .splat) and ``io.scene`` (scenes with object
ids); ``io.arrays`` saves and loads pytrees of arrays (``Params``) as
``.npz``; the MLLM client is ``io.mllm``; ``io.segment_inputs`` reads
segmentation inputs (label masks per camera, boxes as JSON).
"""

from physsplat_jax.io.arrays import TreeFileError as TreeFileError
from physsplat_jax.io.arrays import load_tree as load_tree
from physsplat_jax.io.arrays import save_tree as save_tree
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
from physsplat_jax.io.spz import SpzError as SpzError
from physsplat_jax.io.spz import load_spz as load_spz
from physsplat_jax.io.spz import read_spz_header as read_spz_header
from physsplat_jax.io.spz import save_spz as save_spz
from physsplat_jax.io.scene import SceneFileError as SceneFileError
from physsplat_jax.io.scene import load_scene as load_scene
from physsplat_jax.io.scene import save_scene as save_scene
