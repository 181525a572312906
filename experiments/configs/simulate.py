"""Pipeline settings for ``python -m experiments.simulate`` (CPU-sized).

``get_config()`` returns the defaults; ``SCENE_MOTIONS`` gives each built-in
scene a motion that shows its materials (used when the command line gives
no velocity, impulse or poke). Any field of
``physsplat_jax.pipeline.PipelineConfig`` may be set here.
"""

import ml_collections
from ml_collections import config_dict


def get_config():
  """Defaults: 2 s at 24 fps, 40^3 grid, <= 12k driving particles, 512x384.

  Every scalar field of ``PipelineConfig`` is here, so each can be set on
  the command line (``--config.render=none``), and ``render_config`` holds
  the rasterizer's ``rasterize_mode``; motions (velocities, forces) come
  from ``SCENE_MOTIONS`` or the motion flags.
  """
  c = ml_collections.ConfigDict()
  c.num_frames = 48
  c.fps = 24.0
  c.substeps_per_frame = config_dict.placeholder(int)  # None: CFL
  c.max_substeps_per_frame = 20_000
  c.grid_res = 40
  c.margin = 0.35
  c.max_particles = 12_000
  c.particles_per_cell = 4.0
  c.cfl = 0.4
  c.gravity = 9.8
  c.ground = 'slip'
  c.friction = 0.4
  c.sampling = 'pgas-cvt'  # 'pgas', 'uniform', 'kmeans' (docs/sampling.md)
  c.use_mpdp = True
  c.width = 512
  c.height = 384
  c.camera_index = 0
  c.background = (1.0, 1.0, 1.0)
  c.camera_path = 'fixed'  # 'orbit': the camera turns orbit_degrees
  c.orbit_degrees = 360.0
  # Captures: (xmin, xmax, ymin, ymax, zmin, zmax) in scene units, e.g.
  # --config.roi="(-1,1,-1,1,0,2)"; outside stays static. None: all.
  c.roi = config_dict.placeholder(tuple)
  c.min_opacity = 0.0  # fainter Gaussians stay static
  c.floater_factor = 8.0  # 0: keep floaters in the simulation
  # Support plane height along up [scene units]; None: found.
  c.ground_height = config_dict.placeholder(float)
  c.fill = True
  c.bind_k = 8
  c.use_driver_F = False
  c.render = 'fast'  # 'none': no video or frames
  # Rasterizer settings (fields of physsplat_jax.render.RenderConfig):
  # 'antialiased' for scenes trained with gsplat's antialiased mode
  # (Mip-Splatting), --config.render_config.rasterize_mode=antialiased.
  # backend: 'auto' (Pallas kernels on a GPU, JAX elsewhere), 'jax' or
  # 'pallas'.
  c.render_config = ml_collections.ConfigDict(
    dict(rasterize_mode='classic', backend='auto'))
  c.remat_frames = True
  # MPM stress update: 'auto' (one Pallas kernel on a CUDA GPU, JAX
  # elsewhere), 'jax' or 'pallas' (docs/mpm.md).
  c.constitutive_kernel = 'auto'
  # How a CUDA GPU launches each simulated frame: 'substep' (XLA's
  # default: one CUDA graph per substep), 'frame' (one graph) or 'off'.
  c.gpu_graphs = 'substep'
  c.seed = 0
  return c


# Per built-in scene: motions that make different materials behave
# differently (velocities in m/s in the scene's axes, z up).
SCENE_MOTIONS = {
  # Every object is tossed up and sideways and lands on the table: the jelly
  # wobbles, the rubber ball bounces, the sand pile slumps, the can stays
  # rigid.
  'tabletop': dict(initial_velocity={'': (0.0, 0.25, 1.2)}),
  # A poke on the foliage (PhysDreamer-style point force) for 0.25 s.
  'ficus': dict(forces=[dict(kind='point', object='leaves',
                             vector=(-40.0, 0.0, 0.0), point=None,
                             radius=0.12, start=0.0, end=0.25)]),
  # The donut is dropped onto the board from where it rests, fast.
  'donut': dict(initial_velocity={'donut': (0.0, 0.0, -1.5)}),
}
