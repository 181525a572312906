"""CPU-tiny MPDP config for tests (seconds)."""

from experiments.configs import mpdp


def get_config():
  """Tiny network, few objects and steps."""
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
  return c
