"""CPU-tiny MPDP config for tests (seconds)."""

from experiments.configs import mpdp


def get_config():
  """Tiny network, few objects and steps; a tiny simulator task."""
  c = mpdp.get_config()
  c.model.features = (16, 16)
  c.model.edge_features = 16
  c.model.k_neighbors = 4
  c.model.global_features = 16
  c.model.cond_features = 8
  c.model.head_features = (16,)
  c.data.num_train = 16
  c.data.num_eval = 8
  c.data.num_points = 32
  c.train.num_steps = 4
  c.train.batch_size = 4
  c.train.warmup_steps = 1
  c.train.log_every = 2
  c.train.eval_every = 2
  c.train.checkpoint_every = 2
  c.sim.task.update(dict(
    num_gaussians=96, num_particles=64, num_frames=2, substeps_per_frame=20,
    grid_res=12, E=1e5, width=32, height=24, dtype='float32'))
  c.sim.train_seeds = (0,)
  c.sim.eval_seeds = (10,)
  c.sim.num_steps = 2
  c.sim.learning_rate = 1e-2
  c.sim.checkpoint_every = 1
  return c
