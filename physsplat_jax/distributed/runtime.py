"""Multi-process (multi-host) start-up through ``jax.distributed``.

JAX is multi-controller: the same program runs once per process (usually one
process per host, or per GPU under Slurm), every process sees all devices
of the job through ``jax.devices()`` and its own through
``jax.local_devices()``, and collectives between processes are inserted by
XLA. ``jax.distributed.initialize`` must run before any JAX computation, so
``initialize`` here is the first call of a main.

Where the processes come from:

- explicit flags: ``--coordinator_address=host:port --num_processes=P
  --process_id=i`` (the address of process 0; any free port agreed by all);
- auto-detected under Slurm (``srun``; one process per task) and Open MPI
  4 (``mpirun``): :func:`cluster_environment` sees the launcher and JAX
  reads its variables (and ``JAX_COORDINATOR_ADDRESS``,
  ``JAX_COORDINATOR_PORT`` and ``JAX_LOCAL_DEVICE_IDS`` when the flags
  leave them unset); each process then drives the device of its local
  rank only. Verified with Slurm 22.05 and Open MPI 4.1 on one host
  (docs/distributed.md); Open MPI 5 is not detected, and refused;
- other launchers JAX knows (Cloud TPU pods, Kubernetes, MPI4Py): mode
  'auto' does not see them; ``--distributed=on`` (``mode='on'``) calls
  ``jax.distributed.initialize`` without the flags and JAX detects them;
- nothing: a single process, nothing to initialise.

On CPU, processes exchange collectives over TCP with gloo
(``jax_cpu_collectives_implementation``); ``--cpu_devices=N`` splits each
process's CPU into N devices (``jax_num_cpu_devices``), which is how the
tests check multi-device code on one machine.
"""

from __future__ import annotations

import dataclasses
import numbers
import os
from typing import Sequence

import jax
from absl import flags
from absl import logging

from physsplat_jax.errors import PhysSplatError


class DistributedError(PhysSplatError, ValueError):
  """A bad multi-device or multi-host setting or batch (devices, mesh axes,
  process ids, items that do not stack); the message names it and the
  fix."""


class DistributedStartError(PhysSplatError, RuntimeError):
  """``jax.distributed.initialize`` failed; the message lists what to
  check."""


MODES = ('auto', 'on', 'off')
CPU_COLLECTIVES = ('gloo', 'mpi', 'none')


@dataclasses.dataclass(frozen=True)
class RuntimeInfo:
  """Where this process stands after :func:`initialize`.

  Attributes:
    process_index: this process, ``0 .. process_count - 1``.
    process_count: processes in the job.
    num_devices: devices of the whole job.
    num_local_devices: devices of this process.
    platform: 'cpu', 'gpu' or 'tpu'.
    method: how the processes were found: 'explicit' (flags/arguments),
      'auto' (cluster environment: Slurm, Open MPI; with mode 'on', what
      JAX detects itself, e.g. a Cloud TPU pod)
      or 'single' (no distributed runtime).
  """

  process_index: int
  process_count: int
  num_devices: int
  num_local_devices: int
  platform: str
  method: str

  @property
  def is_main(self) -> bool:
    """True on process 0 (the one that writes files and logs results)."""
    return self.process_index == 0


def cluster_environment() -> str | None:
  """The multi-process launcher JAX can auto-detect, or None.

  Returns 'ompi' under Open MPI 4's ``mpirun`` with more than one rank (the
  first JAX checks), 'slurm' inside an ``srun`` step with more than one
  task, and None otherwise (a single process: an ``sbatch`` script outside
  ``srun``, or a plain shell; Open MPI 5, which JAX does not detect:
  :func:`initialize` refuses it).
  """
  env = os.environ
  if 'OMPI_MCA_orte_hnp_uri' in env and int(
      env.get('OMPI_COMM_WORLD_SIZE', '2')) > 1:
    return 'ompi'
  slurm = ('SLURM_JOB_ID', 'SLURM_STEP_NODELIST', 'SLURM_NTASKS',
           'SLURM_PROCID', 'SLURM_LOCALID')
  if all(k in env for k in slurm) and int(env['SLURM_NTASKS']) > 1:
    return 'slurm'
  return None


def _undetected_launcher() -> str | None:
  """Why this process looks like one of several that no one detects, or
  None: Open MPI 5 (PRRTE) sets no ``OMPI_MCA_orte_hnp_uri``, which JAX's
  detection keys on (jax-ml/jax#14576), so each rank ran the whole job
  alone and every one wrote the outputs."""
  env = os.environ
  size = env.get('OMPI_COMM_WORLD_SIZE', '1')
  if ('OMPI_MCA_orte_hnp_uri' not in env and size.isdigit()
      and int(size) > 1):
    return (f'this process is one of {size} that Open MPI 5 or later '
            'started (OMPI_COMM_WORLD_SIZE), which JAX does not detect: '
            'each would run the whole job alone and write the outputs')
  return None


def initialize(
  coordinator_address: str | None = None,
  num_processes: int | None = None,
  process_id: int | None = None,
  local_device_ids: Sequence[int] | None = None,
  mode: str = 'auto',
  cpu_devices: int | None = None,
  cpu_collectives: str = 'gloo',
  initialization_timeout: int = 300,
) -> RuntimeInfo:
  """Starts JAX's distributed runtime when there is more than one process.

  Must be called before any JAX computation (including ``jax.devices()``).

  Args:
    coordinator_address: ``host:port`` of process 0 (None: auto-detect).
    num_processes: processes in the job (None: auto-detect).
    process_id: this process's index (None: auto-detect).
    local_device_ids: devices this process drives (None: all it sees; JAX
      picks one GPU per process under Slurm/Open MPI).
    mode: 'auto' initialises when an argument above is given or a cluster
      launcher is detected (:func:`cluster_environment`); 'on' always
      (JAX must then be able to auto-detect what is missing); 'off' never.
    cpu_devices: split the CPU into this many devices per process
      (``jax_num_cpu_devices``; for testing on one machine).
    cpu_collectives: CPU collectives between processes: 'gloo' (TCP; works
      everywhere), 'mpi' (needs an MPI library) or 'none'.
    initialization_timeout: seconds to wait for all processes [s].

  Returns:
    :class:`RuntimeInfo`.

  Raises:
    DistributedError: a bad argument (named, with the fix).
    DistributedStartError: JAX was already used before this call, or
      JAX refused the settings. Processes that do not all join within
      ``initialization_timeout`` are aborted by JAX itself (a C++ fatal
      error, DEADLINE_EXCEEDED), which no exception can report: the log
      line before the join names what to check.
  """
  if mode not in MODES:
    raise DistributedError(f'initialize: mode = {mode!r}; use one of {MODES}.')
  if cpu_collectives not in CPU_COLLECTIVES:
    raise DistributedError(
      f'initialize: cpu_collectives = {cpu_collectives!r}; '
      f'use one of {CPU_COLLECTIVES}.')
  if num_processes is not None and num_processes < 1:
    raise DistributedError(
      f'initialize: num_processes = {num_processes} must be '
      '>= 1.')
  if process_id is not None and num_processes is not None and not (
      0 <= process_id < num_processes):
    raise DistributedError(f'initialize: process_id = {process_id} must be in '
                           f'[0, num_processes = {num_processes}).')
  if (isinstance(initialization_timeout, bool)
      or not isinstance(initialization_timeout, numbers.Integral)
      or initialization_timeout < 1):
    raise DistributedError(
      f'initialize: initialization_timeout = {initialization_timeout!r}; '
      'give whole seconds >= 1 (e.g. --initialization_timeout=600 where '
      'processes start minutes apart).')
  if cpu_devices is not None:
    if cpu_devices < 1:
      raise DistributedError(f'initialize: cpu_devices = {cpu_devices} must be '
                             '>= 1.')
    try:
      jax.config.update('jax_num_cpu_devices', int(cpu_devices))
    except RuntimeError as e:
      raise DistributedStartError(
        'initialize(cpu_devices=...) came after JAX was already used in this '
        'process; call physsplat_jax.distributed.initialize first thing in '
        'main (or set XLA_FLAGS=--xla_force_host_platform_device_count=N '
        f'before Python starts). ({e})') from None
  explicit = any(a is not None for a in (coordinator_address, num_processes,
                                         process_id))
  if explicit and num_processes == 1:
    explicit, mode = False, 'off'
  detected = cluster_environment()
  undetected = _undetected_launcher()
  if mode == 'auto' and not (explicit or detected) and undetected:
    raise DistributedError(
      f'initialize: {undetected}. Pass the job explicitly, e.g. mpirun ... '
      "bash -c 'python -m experiments.sweep ... --coordinator_address="
      'HOST:PORT --num_processes=$OMPI_COMM_WORLD_SIZE --process_id='
      "$OMPI_COMM_WORLD_RANK' (HOST: the first rank's host, any free "
      'port), or --distributed=on if your JAX detects this launcher, or '
      '--distributed=off to run each process alone.')
  if mode == 'on' or (mode == 'auto' and (explicit or detected)):
    _check_address(coordinator_address)
    if cpu_collectives != 'none':
      jax.config.update('jax_cpu_collectives_implementation', cpu_collectives)
    if (explicit and coordinator_address is None and detected is None
        and 'JAX_COORDINATOR_ADDRESS' not in os.environ):
      raise DistributedError(
        'initialize: num_processes/process_id given without '
        'coordinator_address and no cluster launcher detected; pass '
        '--coordinator_address=HOST:PORT (process 0\'s host, a free port).')
    # Past this point a process that waits longer than the timeout for the
    # others is aborted inside JAX (a C++ fatal error: DEADLINE_EXCEEDED in
    # RegisterTask), not given an exception, so the hint comes first.
    logging.info(
      'jax.distributed: joining %s as process %s of %s (waits up to %d s '
      'for every process; an abort with DEADLINE_EXCEEDED means not all '
      'joined: start every one with the same --coordinator_address and '
      '--num_processes and its own --process_id, check that process '
      "0's host and port are reachable, or wait longer with "
      '--initialization_timeout)',
      coordinator_address or os.environ.get('JAX_COORDINATOR_ADDRESS',
                                            '(auto-detected)'),
      'auto' if process_id is None else process_id,
      'auto' if num_processes is None else num_processes,
      initialization_timeout)
    try:
      jax.distributed.initialize(
        coordinator_address=coordinator_address, num_processes=num_processes,
        process_id=process_id,
        local_device_ids=(None if local_device_ids is None
                          else list(local_device_ids)),
        initialization_timeout=initialization_timeout)
    except (RuntimeError, ValueError) as e:
      raise DistributedStartError(
        f'jax.distributed.initialize failed ({e}). It must run before any '
        'JAX computation, once per process, and every process needs the '
        'same coordinator address and process count (check '
        '--coordinator_address, --num_processes, --process_id, the '
        'firewall and that process 0 is running).') from None
    method = 'explicit' if explicit else 'auto'
  else:
    method = 'single'
  info = RuntimeInfo(
    process_index=jax.process_index(), process_count=jax.process_count(),
    num_devices=jax.device_count(), num_local_devices=jax.local_device_count(),
    platform=jax.default_backend(), method=method)
  logging.info('distributed runtime (%s): process %d/%d, %d local / %d '
               'global %s devices', info.method, info.process_index,
               info.process_count, info.num_local_devices, info.num_devices,
               info.platform)
  return info


def _check_address(coordinator_address: str | None) -> None:
  """Raises DistributedError unless the coordinator (argument, else
  ``JAX_COORDINATOR_ADDRESS``) is None or ``HOST:PORT``; JAX's own errors
  for a bad one were an IndexError or a failed RPC server."""
  source = 'coordinator_address'
  if coordinator_address is None:
    coordinator_address = os.environ.get('JAX_COORDINATOR_ADDRESS')
    source = 'JAX_COORDINATOR_ADDRESS'
  if coordinator_address is None:
    return
  host, _, port = str(coordinator_address).rpartition(':')
  if not (host and port.isdigit() and 0 < int(port) < 65536):
    raise DistributedError(
      f'initialize: {source} = {coordinator_address!r}; give HOST:PORT, '
      "process 0's host and a free port that every process uses (e.g. "
      '--coordinator_address=10.0.0.1:12355).')


def define_flags(flag_values: flags.FlagValues = flags.FLAGS) -> None:
  """Defines the multi-host flags (call at import time of a main).

  ``--coordinator_address``, ``--num_processes``, ``--process_id``,
  ``--local_device_ids``, ``--distributed`` (auto|on|off),
  ``--initialization_timeout``, ``--cpu_devices`` and
  ``--cpu_collectives``; read them with
  :func:`initialize_from_flags`.
  """
  flags.DEFINE_string(
    'coordinator_address', None, 'host:port of process 0 for '
    'jax.distributed (auto-detected under Slurm/Open MPI; '
    '--distributed=on for a Cloud TPU pod or Kubernetes).',
    flag_values=flag_values)
  flags.DEFINE_integer('num_processes', None, 'Processes in the job '
                       '(auto-detected under Slurm/Open MPI).',
                       flag_values=flag_values)
  flags.DEFINE_integer('process_id', None, 'Index of this process in '
                       '[0, num_processes).', flag_values=flag_values)
  flags.DEFINE_list('local_device_ids', None, 'Devices this process drives '
                    '(default: all it sees; under Slurm/Open MPI JAX picks '
                    'the one of the local rank: give 0,1,2,3 for one '
                    'process driving 4 GPUs).', flag_values=flag_values)
  flags.DEFINE_enum('distributed', 'auto', MODES, 'auto: start '
                    'jax.distributed when flags are given or a launcher is '
                    'detected; on: always; off: never.',
                    flag_values=flag_values)
  flags.DEFINE_integer('initialization_timeout', 300, 'Seconds every '
                       'process waits for all to join jax.distributed '
                       '(JAX aborts the ones left waiting).',
                       flag_values=flag_values)
  flags.DEFINE_integer('cpu_devices', None, 'Split the CPU into this many '
                       'devices per process (testing sharding on one '
                       'machine).', flag_values=flag_values)
  flags.DEFINE_enum('cpu_collectives', 'gloo', CPU_COLLECTIVES,
                    'CPU collectives between processes.',
                    flag_values=flag_values)


def initialize_from_flags(
    flag_values: flags.FlagValues = flags.FLAGS) -> RuntimeInfo:
  """:func:`initialize` with the values of :func:`define_flags`' flags."""
  f = flag_values
  ids = f.local_device_ids
  try:
    ids = None if ids is None else [int(i) for i in ids]
  except ValueError:
    raise DistributedError(
      f'--local_device_ids={",".join(ids)}: give integers, '
      'e.g. --local_device_ids=0,1.') from None
  return initialize(
    coordinator_address=f.coordinator_address,
    num_processes=f.num_processes, process_id=f.process_id,
    local_device_ids=ids, mode=f.distributed, cpu_devices=f.cpu_devices,
    cpu_collectives=f.cpu_collectives,
    initialization_timeout=f.initialization_timeout)
