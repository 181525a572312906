"""Training and fitting through the simulator (above ``pipeline``).

``simtrain``: MPDP trained on trajectory (or image) losses through
:func:`physsplat_jax.pipeline.simulate`, and ``fit_material`` (recover E
from an observed trajectory or video). The supervised MPDP training, which
needs no simulator, is ``physsplat_jax.mpdp.train``.
"""

from physsplat_jax.training import simtrain as simtrain
from physsplat_jax.training.simtrain import Task as Task
from physsplat_jax.training.simtrain import DivergedError as DivergedError
from physsplat_jax.training.simtrain import TrainingError as TrainingError
from physsplat_jax.training.simtrain import TaskConfig as TaskConfig
from physsplat_jax.training.simtrain import fit_material as fit_material
from physsplat_jax.training.simtrain import make_loss as make_loss
from physsplat_jax.training.simtrain import make_tasks as make_tasks
from physsplat_jax.training.simtrain import (
  train_through_simulator as train_through_simulator,
)
from physsplat_jax.training.simtrain import (
  trajectory_errors as trajectory_errors,
)
