"""Pluggable per-frame outputs of a simulation run (files only).

A host loop (:func:`physsplat_jax.pipeline.run`, the PhysGaussian driver in
``experiments/simulate.py``) hands every frame, as a :class:`Frame`, to each
of its writers in turn; each writer keeps what it needs and names its files
on :meth:`~FrameWriter.close`. Writers write to a temporary name and rename
when complete, so a run that stops half-way leaves complete files (the
frames so far) and never a half-written one.

Writers: :class:`VideoOutput` (MP4, GIF fallback), :class:`PngOutput`
(``frames/frame_%04d.png``), :class:`PlyOutput` (``ply/frame_%04d.ply``,
deformed INRIA PLY), :class:`SpzOutput` (``spz/frame_%04d.spz``, deformed
Niantic .spz), :class:`TrajectoryOutput` (``trajectory.npz``).
:func:`write_json` writes a report atomically. :class:`BackgroundWriters`
runs a list of writers off the host loop's thread. :func:`check_output_dir`
and :func:`check_output_file` check an output path before the work (the
writers here and in ``io.video`` / ``io.export`` check theirs).
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import dataclasses
import functools
import inspect
import json
import math
import os
import re
import tempfile
from typing import Any, Protocol, Sequence

import numpy as np
from absl import logging

from physsplat_jax import atomic_files
from physsplat_jax.errors import PhysSplatError
from physsplat_jax.io import export as export_lib
from physsplat_jax.io import paths
from physsplat_jax.io import video as video_lib
from physsplat_jax.types import Gaussians


class OutputError(PhysSplatError, OSError):
  """An output folder or file cannot be written; the message says which."""


@dataclasses.dataclass
class Frame:
  """One frame of a run, as the writers see it (NumPy or jax arrays).

  Attributes:
    index: frame number (0 = initial state).
    time: simulated time [s].
    image: (H, W, 3) RGB in [0, 1], or None when nothing was rendered.
    positions: (Ks, 3) simulated Gaussians' centres (scene coordinates).
    particles: (N, 3) driving-particle positions (scene coordinates).
    gaussians: every Gaussian of the scene at this frame (means deformed),
      or None; with ``covariances`` (K, 3, 3) and ``rotations`` (K, 3, 3)
      the deformed shapes and SH view rotations (for PLY and .spz frames).
  """

  index: int
  time: float
  image: Any = None
  positions: Any = None
  particles: Any = None
  gaussians: Gaussians | None = None
  covariances: Any = None
  rotations: Any = None


class FrameWriter(Protocol):
  """What a host loop needs of an output."""

  def write(self, frame: Frame) -> None:
    ...

  def close(self) -> dict[str, str]:
    """Finishes the files; returns ``{kind: path}`` of what was written."""
    ...


def check_output_dir(path: str) -> str:
  """Creates ``path`` (and parents) and checks it is a writable folder.

  Called before any expensive work so a bad ``--out`` fails at once.

  Raises:
    OutputError: naming the path and the fix.
  """
  path = os.fspath(path)
  if os.path.exists(path) and not os.path.isdir(path):
    raise OutputError(f'output folder {path!r} is a file; give a folder '
                      'name (it is created if missing).')
  try:
    os.makedirs(path, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=path, prefix='.write_test_'):
      pass
  except OSError as e:
    raise OutputError(f'output folder {path!r} cannot be written '
                      f'({e.strerror or e}); choose a writable folder.'
                      ) from None
  return path


def check_output_file(path, error: type[Exception] = OutputError, *,
                      create: bool = False) -> str:
  """:func:`physsplat_jax.io.paths.check_output_file`, as ``error``
  (:class:`OutputError` by default)."""
  return paths.check_output_file(path, error, create=create)


_LOCK = atomic_files.LOCK


@contextlib.contextmanager
def output_lock(out_dir: str):
  """Holds ``out_dir`` for this run while it writes into it
  (:func:`physsplat_jax.atomic_files.hold_folder`).

  A second run into the same folder (another process, or another thread
  of this one) fails at once with a message naming the first run, instead
  of both writing the same files (one run's report listed the other's
  video). A lock file left by a run that has ended (killed) is taken over:
  the lock itself is the kernel's (``flock``), released when its process
  ends. Nested holds by one thread (``simulate_scene`` around ``run``) are
  allowed. While held, temporary files that an earlier, killed run left
  are removed.

  Raises:
    OutputError: another live run holds the folder, or its lock file
      cannot be written.
  """
  with atomic_files.hold_folder(out_dir, OutputError, what='output folder',
                                flag='--out', on_take=_remove_partials):
    yield


def holds_output_dir(*files: str):
  """Decorator of a run that writes into its ``out_dir`` argument: when it
  is not None, the folder is checked (:func:`check_output_dir`, and each of
  ``files`` in it, e.g. ``'report.json'``, before the work) and held
  (:func:`output_lock`) while the run goes on."""

  def decorate(fn):
    signature = inspect.signature(fn)

    @functools.wraps(fn)
    def held(*args, **kwargs):
      bound = signature.bind(*args, **kwargs)
      out_dir = bound.arguments.get('out_dir')
      if out_dir is None:
        return fn(*args, **kwargs)
      check_output_dir(out_dir)
      for name in files:
        check_output_file(os.path.join(out_dir, name))
      with output_lock(out_dir):
        return fn(*args, **kwargs)

    return held

  return decorate


def _remove_partials(out_dir: str) -> None:
  """Removes the temporary files (``paths.partial_path``) of runs that
  were killed before renaming them (the folder is locked: no other run
  writes them now)."""
  for sub in ('', 'frames', 'ply', 'spz'):
    folder = os.path.join(out_dir, sub)
    if not os.path.isdir(folder):
      continue
    for name in os.listdir(folder):
      if paths.PARTIAL.fullmatch(name):
        with contextlib.suppress(OSError):
          os.remove(os.path.join(folder, name))


def write_json(path: str, data: Any) -> str:
  """Writes ``data`` as indented JSON atomically (temporary name, rename).

  Non-finite floats are written as strings ('nan', 'inf') and NumPy values
  as plain numbers, so the file is valid JSON whatever the run produced.

  Raises:
    OutputError: it cannot be written (a full disk: naming the file and
      the fix); nothing is left half-written.
  """
  return paths.write_data(path, json.dumps(jsonable(data), indent=1),
                         OutputError, what='JSON')


def write_failure_report(path: str, report: dict) -> str | None:
  """:func:`write_json` of a failed run's report: an error writing it (the
  disk full for the report too) is logged, not raised, so that the run's
  own error is the one raised. Returns the path, or None."""
  try:
    return write_json(path, report)
  except Exception as e:  # noqa: BLE001 - the run's error is the one raised
    logging.error('%s not written (%s); the run failed with the error '
                  'below', os.path.basename(path), e)
    return None


def jsonable(x):
  """``x`` with NumPy values, tuples and non-finite floats made JSON-safe."""
  if isinstance(x, dict):
    return {str(k): jsonable(v) for k, v in x.items()}
  if isinstance(x, (list, tuple)):
    return [jsonable(v) for v in x]
  if isinstance(x, np.ndarray):
    return jsonable(x.tolist())
  if isinstance(x, (np.floating, np.integer, np.bool_)):
    x = x.item()
  if isinstance(x, float) and not math.isfinite(x):
    return str(x)
  return x


# The largest side libx264 encodes (16386 failed with the imageio-ffmpeg
# binary, 16384 passed).
MAX_VIDEO_SIDE = 16384


class VideoOutput:
  """``video.mp4`` (GIF when no ffmpeg) from the frames' images."""

  def __init__(self, path: str, fps: float):
    self.path = self._final = check_output_file(path)
    if (os.path.splitext(path)[1].lower() != '.gif'
        and video_lib.find_ffmpeg() is None):
      self._final = check_output_file(os.path.splitext(path)[0] + '.gif')
      logging.warning('no ffmpeg (install imageio-ffmpeg, or set '
                      'IMAGEIO_FFMPEG_EXE to an ffmpeg executable): writing '
                      '%s instead of %s', self._final, self.path)
    self._writer = video_lib.VideoWriter(paths.partial_path(self._final),
                                         fps=fps)
    self._failed = False

  def write(self, frame: Frame) -> None:
    if frame.image is not None:
      try:
        self._writer.append(np.clip(np.asarray(frame.image), 0.0, 1.0))
      except BaseException:
        self._failed = True  # (the writer's error is the run's)
        raise

  def close(self) -> dict[str, str]:
    try:
      self._writer.close()
      if self._failed or self._writer.num_frames == 0:
        self._discard()
        return {}
      os.replace(self._writer.path, self._final)
    except BaseException as e:
      self._discard()
      if isinstance(e, OSError) and not isinstance(e, PhysSplatError):
        raise OutputError(f'{self._final}: cannot write the video '
                          f'({paths.os_error_reason(e)})') from None
      raise
    return {'video': self._final}

  def _discard(self) -> None:
    with contextlib.suppress(OSError):
      os.remove(self._writer.path)


def _clear_frames(directory: str, ext: str, written: set[str]) -> None:
  """Removes the ``frame_NNNN.<ext>`` files of ``directory`` that this run
  did not write (``written``: their names; only that pattern, nothing else
  of the user's), so that the folder holds this run's frames only, not a
  longer earlier run's tail. Called when the writer closes, and only when
  it wrote a frame: a run that fails before its first frame leaves an
  earlier run's frames as they were."""
  if not written or not os.path.isdir(directory):
    return
  old = [f for f in os.listdir(directory)
         if re.fullmatch(rf'frame_\d{{4,}}\.{ext}', f) and f not in written]
  for f in old:
    with contextlib.suppress(OSError):
      os.remove(os.path.join(directory, f))
  if old:
    logging.info('removed %d frames of an earlier run from %s', len(old),
                 directory)


class PngOutput:
  """``frames/frame_%04d.png`` (each PNG complete when written; an
  earlier run's other frames in the folder are removed at the end)."""

  def __init__(self, directory: str):
    self.directory = os.fspath(directory)
    check_output_file(os.path.join(self.directory, 'frame_0000.png'))
    self._written: set[str] = set()

  def write(self, frame: Frame) -> None:
    if frame.image is not None:
      img = video_lib.to_uint8(np.clip(np.asarray(frame.image), 0.0, 1.0),
                               self.directory)
      name = video_lib.PNG_PATTERN % frame.index
      os.makedirs(self.directory, exist_ok=True)
      video_lib.save_png(os.path.join(self.directory, name), img)
      self._written.add(name)

  def close(self) -> dict[str, str]:
    _clear_frames(self.directory, 'png', self._written)
    return {'frames': self.directory} if self._written else {}


class DeformedOutput:
  """``<format>/frame_%04d.<format>``: every Gaussian of the scene,
  deformed, one file a frame (each complete when written; an earlier
  run's other frames in the folder are removed at the end). Use
  :class:`PlyOutput` or :class:`SpzOutput`."""

  format = ''  # 'ply' or 'spz': the subclass's

  def __init__(self, directory: str, base: Gaussians):
    self.directory = os.fspath(directory)
    self._pattern = f'frame_%04d.{self.format}'
    check_output_file(os.path.join(self.directory, self._pattern % 0))
    self._save = export_lib.SAVE_DEFORMED[self.format]
    self._base = base
    self._written: set[str] = set()

  def write(self, frame: Frame) -> None:
    if frame.gaussians is None:
      return
    os.makedirs(self.directory, exist_ok=True)
    name = self._pattern % frame.index
    paths.write_atomically(
      os.path.join(self.directory, name),
      lambda tmp: self._save(
        tmp, self._base, frame.gaussians.means, frame.covariances,
        frame.rotations, **self._options()), OutputError,
      what=self.format.upper())
    self._written.add(name)

  def _options(self) -> dict:
    """Keyword options of this frame's save (the subclass's)."""
    return {}

  def close(self) -> dict[str, str]:
    _clear_frames(self.directory, self.format, self._written)
    return {self.format: self.directory} if self._written else {}


class PlyOutput(DeformedOutput):
  """``ply/frame_%04d.ply``: deformed INRIA PLY frames, SH degree 3
  (:func:`~physsplat_jax.io.export.save_deformed_ply`)."""

  format = 'ply'


class SpzOutput(DeformedOutput):
  """``spz/frame_%04d.spz``: deformed Niantic ``.spz`` frames, the
  scene's SH degree, a tenth of a PLY frame or less
  (:func:`~physsplat_jax.io.export.save_deformed_spz`)."""

  format = 'spz'

  def __init__(self, directory: str, base: Gaussians):
    super().__init__(directory, base)
    self._warned: set[str] = set()

  def _options(self) -> dict:
    # Values clamped to the format's ranges (a trained scene's brightest
    # colours, its smallest scales) are mostly the same Gaussians every
    # frame: each field warns once a run (io.spz.encode_spz's ``warned``).
    # gzip's fastest level: 5-6x faster than its default for 3-10 % more
    # bytes (io.spz.encode_spz), a frame's write off the loop's path.
    return {'warned': self._warned, 'compress_level': 1}


class TrajectoryOutput:
  """``trajectory.npz``: ``x`` (T+1, Ks, 3) float32 positions of the
  simulated Gaussians in the input scene's coordinates (frame 0 = initial),
  ``ids`` (Ks,) their rows in the input, ``t`` (T+1,) seconds and, when
  given, ``particles`` (T+1, N, 3) the driving particles. Stored
  uncompressed: float positions deflate by ~13 %, and compressing them
  (1.7 s for a paper-scale run on the 2-core CPU) would sit at the end of
  every run, after the last frame."""

  def __init__(self, path: str, ids):
    self.path = check_output_file(path)
    self._ids = np.asarray(ids, np.int64)
    self.positions: list[np.ndarray] = []
    self.particles: list[np.ndarray] = []
    self.times: list[float] = []

  def write(self, frame: Frame) -> None:
    self.positions.append(np.asarray(frame.positions, np.float32))
    if frame.particles is not None:
      self.particles.append(np.asarray(frame.particles, np.float32))
    self.times.append(float(frame.time))

  def close(self) -> dict[str, str]:
    if not self.positions:
      return {}
    data = dict(x=np.stack(self.positions), ids=self._ids,
                t=np.asarray(self.times, np.float64))
    if self.particles:
      data['particles'] = np.stack(self.particles)
    paths.write_npz(self.path, data, OutputError, what='trajectory')
    return {'trajectory': self.path}


class BackgroundWriters:
  """Writers run on background threads while the host loop goes on.

  Encoding a frame is host work (an 800x800 PNG ~20 ms, an MP4 frame ~16 ms
  on the 2-core CPU), done while the device computes the next frame. Each
  writer has one thread of its own, so its frames stay in order (the
  video appends them in sequence) and the writers need not be
  thread-safe; Pillow, zlib and the pipe to ffmpeg release the GIL. At
  most ``max_pending`` frames wait per writer (their images are the memory
  cost); :meth:`write` then waits for the oldest. A writer's error is
  raised by the next :meth:`write` or by :meth:`close`, after every writer
  has been closed: output is never dropped silently. A writer that failed
  gets no further frames (those already queued for it are skipped).
  """

  def __init__(self, writers: Sequence[FrameWriter], max_pending: int = 4):
    self.writers = list(writers)
    self.max_pending = max(1, int(max_pending))
    self._pools = [concurrent.futures.ThreadPoolExecutor(
      1, thread_name_prefix=f'writer-{type(w).__name__}')
      for w in self.writers]
    self._pending = [collections.deque() for _ in self.writers]
    self._failed = [False] * len(self.writers)

  def _write_one(self, i: int, frame: Frame) -> None:
    """Writer ``i``'s frame, on its own thread (so in order)."""
    if self._failed[i]:
      return
    try:
      self.writers[i].write(frame)
    except BaseException:
      self._failed[i] = True
      raise

  def write(self, frame: Frame) -> None:
    """Queues ``frame`` for every writer (raises a writer's earlier error)."""
    for i, (pool, queue) in enumerate(zip(self._pools, self._pending)):
      while queue and (queue[0].done() or len(queue) >= self.max_pending):
        queue.popleft().result()
      queue.append(pool.submit(self._write_one, i, frame))

  def close(self) -> dict[str, str]:
    """Waits for the queued frames, closes every writer; their files.

    Each writer is closed on its own thread after its last frame, so the
    writers finish side by side (the video's encoder flushes while the
    trajectory is saved). Every writer is closed even if one fails.
    """
    closing = [pool.submit(w.close)
               for pool, w in zip(self._pools, self.writers)]
    files, error = {}, None
    for pool, queue, done in zip(self._pools, self._pending, closing):
      for future in [*queue, done]:
        try:
          result = future.result()
        except Exception as e:  # noqa: BLE001 - re-raised after closing
          error = error or e
        else:
          if future is done:
            files.update(result)
      queue.clear()
      pool.shutdown()
    if error is not None:
      raise error
    return files


def close_after_failure(sink: BackgroundWriters | FrameWriter) -> None:
  """Closes ``sink`` while another error is being raised: what the writers
  finish is kept, and an error of theirs is logged, not raised, so that
  the run's own error (the first one) is the one reported."""
  try:
    sink.close()
  except Exception as e:  # noqa: BLE001 - the error being raised wins
    logging.error('closing the outputs after the error below failed too: '
                  '%s: %s', type(e).__name__, e)


def _size(n: float) -> str:
  for unit in ('bytes', 'KB', 'MB', 'GB'):
    if n < 1024 or unit == 'GB':
      return f'{n:.0f} {unit}' if unit == 'bytes' else f'{n:.1f} {unit}'
    n /= 1024
  return f'{n:.1f} TB'


def check_free_space(out_dir: str, need: dict[str, float]) -> bool:
  """Warns, before the work, when ``out_dir``'s disk has less free space
  than the run's outputs will take (``need``: bytes per output, an
  estimate); returns False then. A run that fills the disk stops there
  with an error naming the file (the frames so far kept), so the warning
  gives the chance to free space first."""
  free = atomic_files.free_bytes(out_dir)
  if free is None:
    return True
  total = sum(need.values())
  if total <= free:
    return True
  parts = ', '.join(f'{k} {_size(v)}' for k, v in need.items() if v)
  logging.warning('%s: this run will write about %s (%s) and its disk has '
                  '%s free; it will stop where the disk is full. Free space, '
                  'or give another --out, fewer frames or a smaller image',
                  out_dir, _size(total), parts, _size(free))
  return False
