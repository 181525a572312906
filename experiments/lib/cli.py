"""One error path for every experiment script.

``cli.run(main)`` replaces ``absl.app.run(main)``: the package's own errors
(:class:`physsplat_jax.errors.PhysSplatError`: bad scene files, configs,
materials, flags, outputs, unstable runs, ...) and OS errors end the script
with one line, ``error: <what, where, how to fix>``, and exit code 1;
usage errors (a flag value the script cannot use) print the same one line
and exit with 2. The
traceback is printed only with ``--debug`` (or ``--verbosity=1``).

It also turns on JAX's persistent compilation cache
(:mod:`physsplat_jax.compile_cache`; ``--compile_cache=DIR`` or ``off``).
"""

from __future__ import annotations

import contextlib
import difflib
import json
import logging as std_logging
import os
import platform
import re
import signal
import subprocess
import sys
import threading
import time

import jax
import ml_collections
from absl import app
from absl import flags
from absl import logging
from ml_collections import config_flags

from physsplat_jax import compile_cache
from physsplat_jax.errors import PhysSplatError
from physsplat_jax.io import outputs
from physsplat_jax.io import paths

_DEBUG = flags.DEFINE_bool('debug', False,
                           'print the full traceback of an error')
_CACHE = flags.DEFINE_string(
  'compile_cache', None, 'persistent compilation cache folder, or "off" '
  '(default: $PHYSSPLAT_JAX_CACHE or ~/.cache/physsplat_jax/jax)')

EXPECTED = (PhysSplatError, OSError)


def define_out(default: str | None, help_text: str) -> flags.FlagHolder:
  """``--out``, or the holder of an ``--out`` another experiment module
  already defined: the tests import several of these modules into one
  process (``benchmark_mpm`` and ``validate_physics``), where a second
  definition raised ``DuplicateFlagError``."""
  if 'out' in flags.FLAGS:
    return flags.FlagHolder(flags.FLAGS, flags.FLAGS['out'])
  return flags.DEFINE_string('out', default, help_text)


# Each config flag's default file (define_config_file), for the message
# about a field that does not exist, and the fields its script reads.
_CONFIG_FILES: dict[str, str | None] = {}
_CONFIG_NEEDS: dict[str, tuple[tuple[str, ...], str | None]] = {}


def _flag_args(argv) -> list[str]:
  """``argv``'s arguments up to absl's ``--``, after which nothing is a
  flag."""
  args = list(argv[1:])
  return args[:args.index('--')] if '--' in args else args


def _given(argv, name: str) -> str | None:
  """The value of the last ``--name=VALUE`` or ``--name VALUE`` in
  ``argv`` (absl takes both) before any ``--``, or None."""
  values = []
  args = _flag_args(argv)
  for i, a in enumerate(args):
    if a.startswith(f'--{name}='):
      values.append(a.split('=', 1)[1])
    elif a == f'--{name}' and i + 1 < len(args):
      values.append(args[i + 1])
  return values[-1] if values else None


def _check_configs() -> None:
  """Each parsed config flag holds a ConfigDict with the fields its script
  needs (:func:`define_config_file`), or a usage error naming the file."""
  for name, (needs, example) in _CONFIG_NEEDS.items():
    if name not in flags.FLAGS:
      continue
    config = flags.FLAGS[name].value
    file = config_flags.get_config_filename(flags.FLAGS[name])
    fits = f'; {example} is one that fits' if example else ''
    if config is None:
      if file:  # (an optional flag's file whose get_config() gave None)
        raise usage_error(f'--{name}={file}: its get_config() returned '
                          f'None; return an ml_collections.ConfigDict{fits}')
      continue
    if type(config).__name__ == '_ErrorConfig':
      config.lock()  # raises the error ml_collections kept (a missing file)
    if not isinstance(config, ml_collections.ConfigDict):
      raise usage_error(
        f'--{name}={file}: its get_config() returned a '
        f'{type(config).__name__}; return an ml_collections.ConfigDict{fits}')
    missing = []
    for path in needs:
      node = config
      for key in path.split('.'):
        node = node.get(key) if isinstance(
          node, ml_collections.ConfigDict) else None
      if node is None:
        missing.append(path)
    if missing:
      raise usage_error(
        f'--{name}={file}: this script reads {", ".join(missing)} from its '
        f'config, which this file does not have{fits}')


def _config_fields(path: str, parents: list[str]) -> list[str] | None:
  """The field names at ``parents`` in the config ``get_config()`` of the
  .py ``path`` returns, or None when that cannot be read."""
  import importlib.util  # noqa: PLC0415 (only on this error path)
  try:
    spec = importlib.util.spec_from_file_location('_config_fields', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    config = module.get_config()
    for key in parents:
      config = config[key]
    return sorted(config.keys())
  except Exception:  # noqa: BLE001 (any failure: the message names the file)
    return None


def _unknown_field(e: Exception, argv) -> str | None:
  """The one-line message for an override of a config field that does not
  exist (ml_collections raises AttributeError / KeyError naming it), or
  None when no ``--NAME.PATH`` argument names that field (then the error
  came from elsewhere, e.g. a bug in a config file, and is not ours to
  word). It offers the nearest field names and names the config file
  whose ``get_config()`` lists them all (``--helpfull`` shows only
  ``--NAME`` itself)."""
  # str(e): the name, quoted, and after ml_collections' "Did you mean"
  # when it has a suggestion.
  field = re.search(r"[A-Za-z_]\w*", str(e))
  field = field and field.group()
  for arg in _flag_args(argv):
    if arg.startswith('--') and '.' in arg.split('=')[0]:
      name, *path = arg[2:].split('=')[0].split('.')
      if field not in path:
        continue
      file = _given(argv, name)
      if file is None:
        file = _CONFIG_FILES.get(name)
      readable = bool(file) and os.path.isfile(file)
      fields = (_config_fields(file, path[:path.index(field)])
                if readable else None)
      near = difflib.get_close_matches(field, fields or (), n=3)
      hint = [f'did you mean {" or ".join(map(repr, near))}?'] if near else []
      if readable:
        hint.append(f'{os.path.relpath(file)} lists the fields')
      return (f'the {name} has no field {field!r} ({arg})'
              + ''.join(f'; {h}' if i == 0 else f' {h}'
                        for i, h in enumerate(hint)))
  return None


@contextlib.contextmanager
def _flag_errors(argv):
  """A bad flag or config override raised inside as one ``error:`` line
  and exit code 2: absl's errors, ml_collections' OSError for a config
  file that does not exist (raised while an override is applied, as
  ``--config=/no/such.py --config.num_frames=2``), and its AttributeError /
  KeyError for a field that does not exist (re-raised when no argument
  names that field: then it is not a usage error)."""
  try:
    yield
  except flags.Error as e:
    text = " ".join(str(e).split())
    none = re.match(r'flag --(\w+)=None: Flag --\w+ must have a value other '
                    'than None', text)
    if 'Error whilst parsing config file' in text:
      # ml_collections puts get_config()'s whole traceback in the message.
      frames = [(f, n) for f, n in re.findall(r'File "([^"]+)", line (\d+)',
                                               text)
                if 'ml_collections' not in f]
      error = re.findall(r'\b(\w+(?:Error|Exception): .*)$', text)
      where = (f'config file {frames[-1][0]}, line {frames[-1][1]}'
               if frames else 'the config file')
      text = (f'{where}: {error[-1] if error else "get_config() failed"}; '
              'fix the file')
    elif none and none.group(1) in _CONFIG_NEEDS:
      name = none.group(1)
      given = _given(argv, name)
      example = _CONFIG_NEEDS[name][1]
      text = (f'--{name}={given}: its get_config() returned None; return '
              'an ml_collections.ConfigDict' if given is not None else
              f'--{name} is required: give a config file'
              + (f', e.g. --{name}={example}' if example else ''))
    else:
      text += '; --helpfull lists the flags'
    print(f'error: {text}', file=sys.stderr)
    sys.exit(2)
  except OSError as e:  # ml_collections: a config .py that does not exist
    match = re.search(r'Failed loading config file (\w+)_config', str(e))
    if match is None:
      raise
    name = match.group(1)
    given = _given(argv, name)
    flag = f'--{name}={given!r}' if given is not None else f'--{name}'
    print(f'error: {flag}: no such .py config file', file=sys.stderr)
    sys.exit(2)
  except SyntaxError as e:  # a config .py that does not parse
    print(f'error: config file {e.filename}, line {e.lineno}: {e.msg}; fix '
          'the file (a .py with get_config())', file=sys.stderr)
    sys.exit(2)
  except (AttributeError, KeyError) as e:
    message = _unknown_field(e, argv)
    if message is None and 'get_config' in str(e):
      config = _given(argv, 'config')
      other = ('; a PhysGaussian JSON goes to --physgaussian'
               if 'physgaussian' in flags.FLAGS else '')
      flag = '--config' if config is None else f'--config={config}'
      message = (f'{flag}: not a config file (a .py defining get_config()'
                 f'{other})')
    if message is None:
      raise
    print(f'error: {message}', file=sys.stderr)
    sys.exit(2)


def define_config_file(name: str, default: str | None, help_text: str,
                       needs: tuple[str, ...] = (),
                       example: str | None = None, **kwargs):
  """``ml_collections.config_flags.DEFINE_config_file``, with a bad
  override (``--config.nosuch=1``, overrides in an order it refuses) as
  one line and exit code 2. Without ``--config=FILE`` on the command line
  ml_collections applies the overrides while the flag is defined, when
  the script is imported (with it, while flags are parsed:
  :func:`parse_flags`), and raised from deep inside itself.

  ``needs``: dotted paths the script reads (``'sim.task'``); after parsing,
  a config without them, or a ``get_config()`` that returns something
  other than a ConfigDict, is a usage error that names ``example``, a
  config file that fits (it was an AttributeError in the script)."""
  _CONFIG_FILES[name] = default
  _CONFIG_NEEDS[name] = (tuple(needs), example)
  with _flag_errors(sys.argv):
    holder = config_flags.DEFINE_config_file(name, default, help_text,
                                             **kwargs)
  # A key flag of the script that defines it, so that --help lists it (it
  # belonged to this module, and only --helpfull showed it).
  # (absl names the main module by sys.argv[0], as its own DEFINEs do).
  module = sys._getframe(1).f_globals['__name__']  # noqa: SLF001
  if module == '__main__':
    module = sys.argv[0]
  flags.FLAGS.register_key_flag_for_module(module, flags.FLAGS[name])
  return holder


def check_output_file(flag: str, path: str | None) -> None:
  """Checks up front that the folder of the output file ``path`` (given
  as ``--flag``) exists or can be created and is writable
  (:func:`physsplat_jax.io.outputs.check_output_dir`), so that a bad
  ``--out`` fails before the work, not after it with a bare OS error.
  Nothing when ``path`` is None or empty.

  Raises:
    OutputError: naming the flag, the folder and the fix.
  """
  if not path:
    return
  try:
    outputs.check_output_dir(os.path.dirname(os.path.abspath(path)))
  except outputs.OutputError as e:
    raise outputs.OutputError(f'--{flag}={path}: {e}') from None


def write_json(path: str | None, result) -> None:
  """Writes ``result`` as indented JSON to ``path`` (its folder created);
  nothing when ``path`` is None or empty. Through a temporary file and a
  rename: an interruption leaves the previous file whole, never half of
  it (scripts that rewrite it after each result keep what they had)."""
  if not path:
    return
  os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
  # (a failed write, a full disk, leaves no temporary file behind)
  paths.write_data(path, json.dumps(result, indent=1), outputs.OutputError,
                   what='JSON')


def machine(devices: bool = True) -> dict:
  """What a benchmark ran on, for its JSON results: the host's name, the
  CPU's model (``/proc/cpuinfo``; ``platform.processor()`` gives only
  'x86_64' or nothing on Linux) and cores and, with ``devices``, JAX's
  version, backend, device kind (``NVIDIA H200``; ``cpu`` on the CPU)
  and device count. ``devices=False`` leaves JAX's backend unstarted (a
  parent process whose children use the GPU)."""
  cpu = platform.processor() or platform.machine()
  try:
    with open('/proc/cpuinfo') as f:
      cpu = next((line.split(':', 1)[1].strip() for line in f
                  if line.startswith('model name')), cpu)
  except OSError:
    pass
  out = dict(host=platform.node(), cpu=cpu, cores=os.cpu_count())
  if devices:
    devs = jax.devices()
    out.update(jax=jax.__version__, backend=jax.default_backend(),
               device_kind=devs[0].device_kind, num_devices=len(devs))
  return out


def last_error(stderr: str) -> str:
  """The line of a failed child process's ``stderr`` that says why: its
  last ``error: ...`` line, else the last ``SomethingError: ...`` of a
  traceback, else its last line (the last line alone was often JAX's note
  on filtered traceback frames, printed after the error)."""
  lines = [ln.strip() for ln in stderr.splitlines() if ln.strip()]
  for pattern in (r'error: ', r'[\w.]*(Error|Exception|Interrupt)\b'):
    found = [ln for ln in lines if re.match(pattern, ln)]
    if found:
      return found[-1]
  return lines[-1] if lines else ''


def _verbose() -> bool:
  try:
    return bool(_DEBUG.value) or flags.FLAGS['verbosity'].value >= 1
  except (flags.UnparsedFlagAccessError, KeyError):
    return False


def _setup(cpu_devices: int | None = None,
           cache_default: str | None = None) -> None:
  """What every script does first: the persistent compilation cache
  (``--compile_cache``, else ``cache_default``, else the user folder); with
  ``cpu_devices``, that many CPU devices if the machine has as many cores
  (before JAX starts; not when ``XLA_FLAGS`` or an earlier setting chose)."""
  compile_cache.enable_compilation_cache(
    _CACHE.value if _CACHE.value is not None else cache_default)
  for logger, quiet in ((logging.get_absl_logger(), _QuietOrbax),
                        (std_logging.getLogger('jax._src.xla_bridge'),
                         _QuietBackendProbe)):
    if not any(isinstance(f, quiet) for f in logger.filters):
      logger.addFilter(quiet())
  if (cpu_devices and (os.cpu_count() or 1) >= cpu_devices
      and 'device_count' not in os.environ.get('XLA_FLAGS', '')
      and jax.config.jax_num_cpu_devices < cpu_devices):
    try:
      jax.config.update('jax_num_cpu_devices', cpu_devices)
    except RuntimeError:  # JAX has started: keep what it has
      pass


class _QuietOrbax(std_logging.Filter):
  """Orbax's own log lines: its INFO lines dropped (97 of a short training
  run's 103), its warnings and errors kept without their tracebacks (a
  full disk logged four, above the one-line error that names the file
  and the fix); all of it with ``--debug`` or ``-v 1``."""

  def filter(self, record):
    if f'{os.sep}orbax{os.sep}' not in record.pathname or _verbose():
      return True
    if record.levelno < std_logging.WARNING:
      return False
    record.exc_info = record.exc_text = None
    return True


class _QuietBackendProbe(std_logging.Filter):
  """JAX's INFO line for each platform it probed and did not find
  ("Unable to initialize backend 'tpu': ... libtpu.so"): on every machine
  without that platform, and printed by the backend's thread
  (:func:`start_backend`) after a script's one-line error. Kept with
  ``--debug`` or ``-v 1``."""

  def filter(self, record):
    return (record.levelno >= std_logging.WARNING or _verbose()
            or not record.getMessage().startswith(
              'Unable to initialize backend'))


def guard(main, cpu_devices: int | None = None,
          cache_default: str | None = None, fast_exit: bool = False):
  """``main`` with the package's errors turned into one line and exit 1.

  ``fast_exit``: when ``main`` returns (no error), flush the logs and the
  standard streams and end the process at once (``os._exit(0)``), without
  the interpreter's and JAX's teardown (0.2 s on the 2-core VM, about 0.85 s
  after a paper-scale run on an H200, where the GPU client is torn down).
  For scripts whose output is complete when ``main`` returns: every file
  closed, no thread left with work (the pipeline's writers are closed by
  then).
  """

  def wrapped(argv):
    _setup(cpu_devices, cache_default)
    try:
      with _sigterm_as_interrupt():
        return _main(argv)
    finally:
      _join_backend()

  def _main(argv):
    try:
      result = main(argv)
      if fast_exit and not result:
        logging.flush()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
      return result
    except app.UsageError as e:
      if _verbose():
        raise
      print(f'error: {e}', file=sys.stderr)
      sys.exit(2)
    except EXPECTED as e:
      if _verbose():
        raise
      logging.flush()
      print(f'error: {e}', file=sys.stderr)
      sys.exit(1)
    except RuntimeError as e:
      if _verbose() or 'RESOURCE_EXHAUSTED' not in str(e):
        raise
      logging.flush()
      print(f'error: {out_of_memory_message(e)}', file=sys.stderr)
      sys.exit(1)
    except Terminated:
      logging.flush()
      print('error: terminated (SIGTERM)', file=sys.stderr)
      sys.exit(128 + signal.SIGTERM)
    except KeyboardInterrupt:
      print('error: interrupted', file=sys.stderr)
      sys.exit(130)

  return wrapped


def out_of_memory_message(e: BaseException) -> str:
  """One line for XLA's RESOURCE_EXHAUSTED (a run too large for the
  device's memory): what XLA said and what to make smaller."""
  said = str(e).strip().splitlines()[0] if str(e).strip() else ''
  said = said.split('RESOURCE_EXHAUSTED:', 1)[-1].strip()
  return (f'out of memory ({said[:200]}): the run holds more than the '
          'device has. Make it smaller: --config.max_particles, '
          '--config.grid_res, --config.width / --config.height (frames '
          'rendered), fewer frames or substeps per differentiated call; '
          'or free the device (another process on the GPU: '
          'XLA_PYTHON_CLIENT_PREALLOCATE=false). --debug shows where')


class Terminated(KeyboardInterrupt):
  """SIGTERM (a batch system's time limit or preemption, ``kill``) raised
  in the main thread while a script runs (:func:`guard`). A
  KeyboardInterrupt, so that it takes Ctrl-C's way out: the pipeline closes
  its writers and records the stop in ``report.json``; training saves the
  step it reached. The process then exits with 143 (128 + SIGTERM)."""


class _Term(threading.local):
  raised = False  # a Terminated is on its way out: cleanup runs


_TERM = _Term()


def _raise_terminated(signum, frame):
  """The first SIGTERM raises :class:`Terminated`; one more while that
  unwinds (the writers closing, a checkpoint being saved) is only logged,
  so the cleanup completes (it was interrupted, and the output lost).
  Ctrl-C still interrupts it, and SIGKILL (a batch system's end after its
  grace period) ends the process."""
  del signum, frame
  if _TERM.raised:
    logging.warning('SIGTERM again: still closing the outputs (Ctrl-C or '
                    'SIGKILL ends at once, losing them)')
    return
  _TERM.raised = True
  raise Terminated('SIGTERM')


def catch_sigterm() -> None:
  """Installs the SIGTERM handler of :func:`guard` again, inside a guarded
  script, after something replaced it at the C level: ``jax.distributed``'s
  preemption service installs its own, which swallowed SIGTERM (the
  process ran on until SIGKILL) while ``signal.getsignal`` still named
  ours. Nothing outside a guard (where Python's handler is another) or off
  the main thread."""
  if (threading.current_thread() is threading.main_thread()
      and signal.getsignal(signal.SIGTERM) is _raise_terminated):
    signal.signal(signal.SIGTERM, _raise_terminated)


def run_child(cmd, **kwargs) -> subprocess.CompletedProcess:
  """``subprocess.run(cmd, capture_output=True, text=True, **kwargs)``
  that hands an interruption on to the child: on Ctrl-C or SIGTERM
  (:class:`Terminated`) the child gets the same signal and up to 30 s to
  end in order (a guarded script closes its writers and writes
  ``report.json``) before it is killed; ``subprocess.run`` killed it
  after 0.25 s."""
  with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                        text=True, **kwargs) as p:
    try:
      out, err = p.communicate()
    except KeyboardInterrupt as e:
      p.send_signal(signal.SIGTERM if isinstance(e, Terminated)
                    else signal.SIGINT)
      try:
        p.communicate(timeout=30)
      except subprocess.TimeoutExpired:
        p.kill()
        p.communicate()
      raise
  return subprocess.CompletedProcess(cmd, p.returncode, out, err)


@contextlib.contextmanager
def _sigterm_as_interrupt():
  """SIGTERM raises :class:`Terminated` in the main thread while the block
  runs (before, the process died at once: frames still queued for the
  writers, ``report.json`` and training since the last checkpoint were
  lost). Left alone outside the main thread or where someone else set a
  handler."""
  if (threading.current_thread() is not threading.main_thread()
      or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL):
    yield
    return
  _TERM.raised = False
  signal.signal(signal.SIGTERM, _raise_terminated)
  try:
    yield
  finally:
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    _TERM.raised = False


def process_age() -> float | None:
  """Seconds since this process started (Python's start, its imports and
  JAX's), from ``/proc``; None where there is no ``/proc`` (not Linux)."""
  try:
    with open('/proc/self/stat') as f:
      # Field 22, counted after the command name (which may hold spaces).
      start = float(f.read().rpartition(')')[2].split()[19])
    with open('/proc/uptime') as f:
      uptime = float(f.read().split()[0])
  except (OSError, ValueError, IndexError):
    return None
  return max(0.0, uptime - start / os.sysconf('SC_CLK_TCK'))


def start_backend() -> threading.Thread:
  """Starts JAX's backend (``jax.devices()``) on a thread: on a GPU the
  client's start (driver, context, memory pool) then overlaps what the
  script does before its first JAX call (flags, config, reading the scene);
  the first call waits for it. Errors are left to that first call.
  :func:`guard` waits for the thread before the script ends (a process
  that ends while the backend starts aborts)."""
  global _BACKEND

  def start():
    try:
      jax.devices()
    except Exception:  # noqa: BLE001 - the main thread's call reports it
      pass

  _BACKEND = threading.Thread(target=start, name='jax-backend', daemon=True)
  _BACKEND.start()
  return _BACKEND


_BACKEND: threading.Thread | None = None


def start_run() -> dict:
  """What a pipeline script calls first in ``main``: the process's age so
  far (:func:`process_age`: Python and the imports), JAX's backend started
  (:func:`start_backend`) and the clock; pass it to
  ``experiments.lib.simulate.run_scene(process=...)`` for the report's
  ``process_seconds``."""
  started = process_age()
  start_backend()
  return dict(start_s=started, main_t0=time.perf_counter())


def _join_backend() -> None:
  if _BACKEND is not None:
    _BACKEND.join()


def usage_error(message: str) -> app.UsageError:
  """A usage error (exit code 2) with ``message``."""
  return app.UsageError(message, exitcode=2)


def positive_ints(name: str, values) -> list[int]:
  """A list flag's values as integers >= 1, or a usage error naming the
  flag (``--sizes=0`` was an IndexError from inside the solver)."""
  try:
    out = [int(v) for v in values]
  except ValueError:
    out = []
  if not out or min(out) < 1:
    raise usage_error(f'--{name}={",".join(map(str, values))}: give whole '
                      'numbers >= 1 separated by commas')
  return out


def parse_flags(argv):
  """absl's flag parsing with a bad flag (an unknown one, a value of the
  wrong type, a required one missing, an override of a config field that
  does not exist, a config file of the wrong kind: ``define_config_file``)
  as one ``error:`` line and exit code 2, as the scripts' other usage
  errors (absl printed 'FATAL Flags parsing error' and exited 1); and
  ``--help`` exits 0 (absl's exits 1)."""
  try:
    with _flag_errors(argv):  # (--config=FILE --config.nosuch=1: here)
      rest = flags.FLAGS(argv)
      _check_configs()
  except app.UsageError as e:  # from _check_configs
    print(f'error: {e}', file=sys.stderr)
    sys.exit(2)
  except SystemExit as e:  # absl's --help and friends exit 1 after printing
    asked = {'--help', '-h', '-?', '--helpshort', '--helpfull', '--helpxml'}
    if e.code == 1 and asked & set(_flag_args(argv)):
      sys.exit(0)
    raise
  return rest


def run(main, cpu_devices: int | None = None,
        cache_default: str | None = None, fast_exit: bool = False) -> None:
  """``absl.app.run(main)`` with :func:`guard` and :func:`parse_flags`.

  ``cpu_devices=2`` (the pipeline scripts) gives a CPU process a second
  device, on which ``pipeline.run`` renders each frame while the first
  simulates the next (``render_device='auto'``). ``cache_default``: the
  compilation cache folder when ``--compile_cache`` is not given (None:
  the user folder; ``'off'`` for the benchmarks that report compile
  times, so that a second run measures compilation again). ``fast_exit``:
  see :func:`guard`.
  """
  app.run(guard(main, cpu_devices, cache_default, fast_exit),
          flags_parser=parse_flags)
