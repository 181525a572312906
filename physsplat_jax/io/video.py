"""Video and image outputs: streaming MP4, GIF fallback, PNG frames.

MP4 is H.264 (``libx264``) in ``yuv420p``, the combination every browser and
player decodes, written by an ffmpeg process (the command of
``imageio_ffmpeg.write_frames``) that gets the frames one at a time, so a
simulation can stream its renders without keeping them in memory; ffmpeg's
failure (an output it cannot open, an unknown codec) is raised as a
:class:`VideoError` quoting its reason, never lost. ``yuv420p`` stores
colour at half resolution, so widths and heights must be even: odd sizes
are padded by repeating the last row/column (never rescaled). The ffmpeg
binary ships inside the ``imageio-ffmpeg`` wheel; ``IMAGEIO_FFMPEG_EXE``
overrides it. When no ffmpeg can be found, :class:`VideoWriter` logs a
warning and writes an animated GIF (Pillow) next to the requested path
instead.

Frames are ``(H, W, 3)`` arrays (NumPy or JAX), either float in ``[0, 1]``
(clipped, then rounded to 8 bits) or ``uint8``; NaNs, float frames in
0..255, other shapes or dtypes, and output paths that cannot be written
are rejected with a message naming the frame or the file.

Example::

  with VideoWriter('out/drop.mp4', fps=30) as video:
    for t in range(num_frames):
      video.append(render_frame(t))
"""

from __future__ import annotations

import contextlib
import fractions
import logging
import os
import re
import shutil
import subprocess
import tempfile
import warnings

import numpy as np

from physsplat_jax.errors import PhysSplatError
from physsplat_jax.io import paths

PathLike = str | os.PathLike

logger = logging.getLogger(__name__)

DEFAULT_FPS = 30.0
# imageio-ffmpeg quality in [0, 10] (10 = best); 8 looks clean on renders.
DEFAULT_QUALITY = 8.0
PNG_PATTERN = 'frame_%04d.png'
# A float frame whose maximum is above this is taken for 0..255 values (it
# would come out white): refused. Renders in [0, 1] overshoot by far less.
FLOAT_FRAME_MAX = 2.0


class VideoError(PhysSplatError, ValueError):
  """A frame or a setting that cannot be written."""


# -----------------------------------------------------------------------------
# Frames.


def to_uint8(frame, what: str = 'frame') -> np.ndarray:
  """Checks one RGB frame and converts it to ``uint8``.

  Args:
    frame: (H, W, 3) float in [0, 1] (values outside are clipped) or uint8;
      NumPy or JAX.
    what: name used in error messages (e.g. ``'frame 12'``).

  Returns:
    (H, W, 3) C-contiguous ``uint8`` array.

  Raises:
    VideoError: wrong shape or dtype, non-finite values, or float values
      far above 1 (0..255 given as float).
  """
  a = np.asarray(frame)
  if a.ndim != 3 or a.shape[2] != 3 or a.shape[0] < 1 or a.shape[1] < 1:
    raise VideoError(
      f'{what}: shape {a.shape}; expected (H, W, 3) RGB (drop an alpha '
      'channel with frame[..., :3])'
    )
  if a.dtype == np.uint8:
    return np.ascontiguousarray(a)
  if a.dtype.name == 'bfloat16':
    a = a.astype(np.float32)
  if a.dtype == np.bool_ or not (
    np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)
  ):
    raise VideoError(
      f'{what}: dtype {a.dtype}; expected float in [0, 1] or uint8'
    )
  if np.issubdtype(a.dtype, np.integer):
    raise VideoError(
      f'{what}: integer dtype {a.dtype}; pass uint8 (0..255) or float in '
      '[0, 1] (e.g. frame / 255.0)'
    )
  # NaN propagates through min and max, and an inf is one of them: two
  # reductions instead of a boolean frame (a frame per video frame).
  hi = a.max()
  if not (np.isfinite(a.min()) and np.isfinite(hi)):
    bad = ~np.isfinite(a)
    i, j, _ = np.argwhere(bad)[0]
    raise VideoError(
      f'{what}: {int(bad.sum())} non-finite values (first at pixel row {i}, '
      f'column {j}); the render produced NaN/inf'
    )
  if hi > FLOAT_FRAME_MAX:
    raise VideoError(
      f'{what}: float values up to {float(hi):g}; expected [0, 1] (values '
      'above 1 come out white). For 0..255 values pass frame / 255.0, or '
      'frame.astype(np.uint8)'
    )
  # In place after the one copy: clip, scale, round half to even (as
  # np.round), then the cast (C-contiguous, as astype makes it).
  f = np.clip(a, 0.0, 1.0, dtype=np.float32 if a.dtype.itemsize <= 4
              else a.dtype)
  f *= 255.0
  np.rint(f, out=f)
  return f.astype(np.uint8, order='C')


def pad_to_even(frame: np.ndarray) -> np.ndarray:
  """Pads (H, W, C) to even H and W by repeating the last row/column."""
  h, w = frame.shape[:2]
  ph, pw = h % 2, w % 2
  if not (ph or pw):
    return frame
  return np.ascontiguousarray(
    np.pad(frame, ((0, ph), (0, pw), (0, 0)), mode='edge')
  )


def _check_fps(fps) -> float:
  fps = float(fps)
  if not (np.isfinite(fps) and fps > 0):
    raise VideoError(f'fps must be a positive number, got {fps}')
  return fps


def find_ffmpeg() -> str | None:
  """Path of a usable ffmpeg executable, or None.

  Uses ``imageio_ffmpeg.get_ffmpeg_exe()`` (the binary in its wheel, or
  ``IMAGEIO_FFMPEG_EXE``) and checks that the file exists. An
  ``IMAGEIO_FFMPEG_EXE`` that names no executable is logged as such (it
  hides the wheel's binary).
  """
  try:
    import imageio_ffmpeg
  except ImportError:
    return None
  try:
    exe = imageio_ffmpeg.get_ffmpeg_exe()
  except RuntimeError:
    return None
  if os.path.isfile(exe) and os.access(exe, os.X_OK):
    return exe
  found = shutil.which(exe)
  env = os.environ.get('IMAGEIO_FFMPEG_EXE')
  if found is None and env:
    logger.warning('IMAGEIO_FFMPEG_EXE=%s is not an ffmpeg executable; fix '
                   'it, or unset it to use the ffmpeg of imageio-ffmpeg',
                   env)
  return found


@contextlib.contextmanager
def _quiet_fork():
  # JAX warns on every fork; subprocess execs ffmpeg right after forking,
  # which is safe.
  with warnings.catch_warnings():
    warnings.filterwarnings('ignore', message='os.fork',
                            category=RuntimeWarning)
    yield


def _check_output(path, create: bool = False) -> str:
  """:func:`physsplat_jax.io.paths.check_output_file`, as VideoError."""
  return paths.check_output_file(path, VideoError, what='video or image',
                                 create=create)


def _ffmpeg_reason(log: str) -> str:
  """ffmpeg's error lines, without their ``[muxer @ 0x...]`` prefixes."""
  lines = [re.sub(r'^\[[^\]]*\]\s*', '', ln).strip().rstrip('.')
           for ln in log.splitlines()]
  reason = '; '.join(ln for ln in lines if ln)[-600:]
  return reason or 'no message'


# -----------------------------------------------------------------------------
# Streaming writer.


class VideoWriter:
  """Streams RGB frames into an MP4 (H.264, yuv420p) or a GIF.

  The container follows the file extension: ``.mp4`` (also ``.mov``,
  ``.mkv``) through ffmpeg, ``.gif`` through Pillow. If ffmpeg is not
  available, an ``.mp4`` request falls back to ``<stem>.gif`` with a logged
  warning; :attr:`path` is the file actually written. GIF frames are kept in
  memory until :meth:`close` (Pillow writes a GIF in one go).

  Use as a context manager, or call :meth:`close` (an unclosed MP4 is
  truncated).

  Attributes:
    path: the file being written.
    format: ``'mp4'`` or ``'gif'``.
    fps: frames per second.
    num_frames: frames appended so far.
    size: (width, height) of the written frames (even for MP4), or None
      before the first frame.
  """

  def __init__(
    self,
    path: PathLike,
    fps: float = DEFAULT_FPS,
    *,
    quality: float = DEFAULT_QUALITY,
    codec: str = 'libx264',
    allow_gif_fallback: bool = True,
  ):
    """Opens a writer (ffmpeg starts at the first frame).

    Args:
      path: output file; ``.mp4``/``.mov``/``.mkv`` or ``.gif``.
      fps: frames per second (> 0).
      quality: imageio-ffmpeg quality, 0 (worst) .. 10 (best).
      codec: ffmpeg video codec for MP4.
      allow_gif_fallback: write a GIF when ffmpeg is missing (else raise).

    Raises:
      VideoError: unknown extension, bad fps, no ffmpeg and no fallback, or
        a path that cannot be written (a folder, a file in the way).
    """
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    self.fps = _check_fps(fps)
    if not 0.0 <= float(quality) <= 10.0:
      raise VideoError(f'quality must be in [0, 10], got {quality}')
    self._quality = float(quality)
    self._codec = codec
    if ext in ('.mp4', '.mov', '.mkv', '.m4v'):
      self._ffmpeg = find_ffmpeg()
      if self._ffmpeg is None:
        if not allow_gif_fallback:
          raise VideoError(
            f'{path}: no ffmpeg found (pip install imageio-ffmpeg, or set '
            'IMAGEIO_FFMPEG_EXE); write a .gif instead'
          )
        gif = os.path.splitext(path)[0] + '.gif'
        logger.warning(
          'VideoWriter: ffmpeg is not available (install imageio-ffmpeg or '
          'set IMAGEIO_FFMPEG_EXE); writing a GIF instead: %s', gif)
        path, self.format = gif, 'gif'
      else:
        self.format = 'mp4'
    elif ext == '.gif':
      self.format = 'gif'
    else:
      raise VideoError(
        f'{path}: unknown video extension {ext!r}; use .mp4 (H.264) or .gif'
      )
    self.path = _check_output(path)
    self.num_frames = 0
    self.size: tuple[int, int] | None = None
    self._input_size: tuple[int, int] | None = None
    self._proc: subprocess.Popen | None = None
    self._log = None  # ffmpeg's stderr (a temporary file)
    self._existed = True
    self._gif_frames: list[np.ndarray] = []
    self._closed = False

  def __enter__(self) -> VideoWriter:
    return self

  def __exit__(self, exc_type, exc, tb) -> None:
    if exc_type is None:
      self.close()
      return
    try:  # the error in the with-block is the one to report
      self.close()
    except VideoError as e:
      logger.warning('VideoWriter: %s', e)

  def _open_ffmpeg(self, width: int, height: int) -> None:
    """Starts ffmpeg as ``imageio_ffmpeg.write_frames`` does (same command),
    with its error output kept, so that a failure is raised, not lost."""
    _check_output(self.path, create=True)
    # 1 - quality / 10 as crf 0..51 (libx264) or q:v 1..31 (others).
    q = 1.0 - self._quality / 10.0
    rate = (['-crf', str(int(q * 51))] if self._codec == 'libx264'
            else ['-qscale:v', str(int(q * 30) + 1)])
    fps = fractions.Fraction(self.fps).limit_denominator()
    cmd = [self._ffmpeg, '-y', '-f', 'rawvideo', '-vcodec', 'rawvideo',
           '-s', f'{width}x{height}', '-pix_fmt', 'rgb24', '-r', str(fps),
           '-i', '-', '-an', '-vcodec', self._codec, '-pix_fmt', 'yuv420p',
           *rate, '-v', 'error', self.path]
    self._existed = os.path.lexists(self.path)
    self._log = tempfile.TemporaryFile()  # a file: a pipe could fill up
    try:
      with _quiet_fork():
        self._proc = subprocess.Popen(  # own session: Ctrl-C ends the file
          cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
          stderr=self._log, start_new_session=True)
    except OSError as e:
      self._log.close()
      raise VideoError(f'{self.path}: cannot start ffmpeg {self._ffmpeg!r} '
                       f'({e.strerror or e}); set IMAGEIO_FFMPEG_EXE to a '
                       'working ffmpeg, or write a .gif') from None

  def _finish_ffmpeg(self) -> None:
    """Ends ffmpeg's input, waits; raises its error (removing a partial
    file it made) if it failed."""
    proc, self._proc = self._proc, None
    try:
      proc.stdin.close()
    except OSError:  # ffmpeg has gone: its exit status says why
      pass
    rc = proc.wait()
    self._log.seek(0)
    log = self._log.read().decode('utf-8', 'replace')
    self._log.close()
    if rc == 0:
      if log.strip():
        logger.warning('ffmpeg (%s): %s', self.path, _ffmpeg_reason(log))
      return
    if not self._existed and os.path.isfile(self.path):
      os.remove(self.path)
    raise VideoError(
      f'{self.path}: ffmpeg failed (exit status {rc}): {_ffmpeg_reason(log)}'
      f'; nothing was written. Check the output path and the codec '
      f'({self._codec!r})'
    )

  def append(self, frame) -> None:
    """Adds one frame.

    Args:
      frame: (H, W, 3) float in [0, 1] or uint8; every frame must have the
        size of the first.

    Raises:
      VideoError: bad frame, a size change, a closed writer, or ffmpeg
        failed (its reason quoted).
    """
    if self._closed:
      raise VideoError(f'{self.path}: append() after close()')
    what = f'{self.path}: frame {self.num_frames}'
    img = to_uint8(frame, what)
    hw = img.shape[:2]
    if self._input_size is None:
      self._input_size = hw
    elif hw != self._input_size:
      raise VideoError(
        f'{what}: size {hw[1]}x{hw[0]} differs from the first frame '
        f'{self._input_size[1]}x{self._input_size[0]} (W x H); all frames '
        'of a video must have one size'
      )
    if self.format == 'mp4':
      img = pad_to_even(img)
      if self._proc is None:
        self._open_ffmpeg(img.shape[1], img.shape[0])
      try:
        self._proc.stdin.write(img)
        stopped = self._proc.poll() is not None  # it ends only at close
      except OSError:  # a broken pipe: ffmpeg stopped
        stopped = True
      if stopped:
        self._closed = True
        self._finish_ffmpeg()
        raise VideoError(f'{self.path}: ffmpeg stopped at {what}; nothing '
                         'was written')
    else:
      self._gif_frames.append(img)
    self.size = (img.shape[1], img.shape[0])
    self.num_frames += 1

  def close(self) -> None:
    """Finishes the file (idempotent). A writer with no frames writes none.

    Raises:
      VideoError: ffmpeg failed (its reason quoted); nothing was written.
    """
    if self._closed:
      return
    self._closed = True
    if self.format == 'mp4':
      if self._proc is not None:
        self._finish_ffmpeg()
      return
    if self._gif_frames:
      _write_gif(self.path, self._gif_frames, self.fps)
      self._gif_frames = []


def _write_gif(path: str, frames: list[np.ndarray], fps: float) -> None:
  from PIL import Image

  _check_output(path, create=True)
  images = [Image.fromarray(f) for f in frames]
  # GIF delays are in 1/100 s; Pillow takes milliseconds.
  duration = max(int(round(1000.0 / fps)), 10)
  try:
    images[0].save(path, save_all=True, append_images=images[1:],
                   duration=duration, loop=0, optimize=False)
  except OSError as e:
    raise VideoError(f'{path}: cannot write the GIF ({e.strerror or e}); '
                     'choose a writable file') from None


# -----------------------------------------------------------------------------
# Whole-array helpers.


def _frames_array(frames, what: str):
  if isinstance(frames, (list, tuple)):
    if not frames:
      raise VideoError(f'{what}: no frames given')
    return frames
  a = np.asarray(frames)
  if a.ndim != 4:
    raise VideoError(
      f'{what}: frames have shape {a.shape}; expected (T, H, W, 3)'
    )
  if a.shape[0] == 0:
    raise VideoError(f'{what}: no frames given (T = 0)')
  return a


def write_video(
  path: PathLike, frames, fps: float = DEFAULT_FPS, **kwargs
) -> str:
  """Writes a whole sequence as MP4 (or GIF, by extension or fallback).

  Args:
    path: output file (``.mp4`` or ``.gif``).
    frames: (T, H, W, 3) array or a list of (H, W, 3) frames (float in
      [0, 1] or uint8).
    fps: frames per second.
    **kwargs: passed to :class:`VideoWriter` (``quality``, ``codec``,
      ``allow_gif_fallback``).

  Returns:
    The path written (a ``.gif`` if ffmpeg was missing).
  """
  frames = _frames_array(frames, os.fspath(path))
  with VideoWriter(path, fps, **kwargs) as video:
    for f in frames:
      video.append(f)
  return video.path


def read_video(path: PathLike) -> np.ndarray:
  """Reads an MP4 (ffmpeg) or GIF back as (T, H, W, 3) uint8 (for checks)."""
  path = os.fspath(path)
  if not os.path.isfile(path):
    raise VideoError(f'{path}: no such file')
  if path.lower().endswith('.gif'):
    from PIL import Image
    from PIL import ImageSequence

    with Image.open(path) as im:
      return np.stack([np.asarray(f.convert('RGB'))
                       for f in ImageSequence.Iterator(im)])
  import imageio_ffmpeg

  gen = imageio_ffmpeg.read_frames(path, pix_fmt='rgb24')
  with _quiet_fork():
    meta = next(gen)
  w, h = meta['size']
  frames = [np.frombuffer(b, np.uint8).reshape(h, w, 3) for b in gen]
  if not frames:
    return np.zeros((0, h, w, 3), np.uint8)
  return np.stack(frames)


def save_png(path: PathLike, image, compress_level: int = 1) -> None:
  """Writes one (H, W, 3) float [0, 1] or uint8 image as PNG.

  Also accepts (H, W) grey or (H, W, 4) RGBA floats/uint8.
  ``compress_level`` (zlib, 0-9): 1 by default, 3.6x faster than Pillow's
  6 on an 800x800 render (20 against 72 ms on the 2-core CPU) for files
  25-30 % larger; video frames are written by the hundred.
  """
  from PIL import Image

  path = os.fspath(path)
  a = np.asarray(image)
  if a.ndim == 2:
    img = to_uint8(np.repeat(a[..., None], 3, axis=2), path)
  elif a.ndim == 3 and a.shape[2] == 4:
    rgb = to_uint8(a[..., :3], path)
    alpha = to_uint8(np.repeat(a[..., 3:], 3, axis=2), path)[..., :1]
    img = np.concatenate([rgb, alpha], axis=2)
  else:
    img = to_uint8(a, path)
  _check_output(path, create=True)
  # (a temporary file renamed: a full disk leaves the earlier PNG whole,
  # not an empty one)
  paths.write_atomically(
    path, lambda tmp: Image.fromarray(img).save(
      tmp, format='PNG', compress_level=compress_level), VideoError,
    what='PNG')


def load_png(path: PathLike) -> np.ndarray:
  """Reads a PNG as (H, W, 3) uint8 RGB (for checks)."""
  from PIL import Image

  with Image.open(os.fspath(path)) as im:
    return np.asarray(im.convert('RGB'))


class PngFrameWriter:
  """Writes frames as ``directory/frame_0000.png``, ... (streaming).

  Attributes:
    directory: output folder (created).
    pattern: printf-style file name with one integer field.
    num_frames: frames written so far.
    paths: files written.
  """

  def __init__(self, directory: PathLike, pattern: str = PNG_PATTERN,
               start: int = 0):
    try:
      pattern % 0
    except (TypeError, ValueError) as e:
      raise VideoError(
        f'pattern {pattern!r} needs one integer field such as %04d'
      ) from e
    self.directory = os.fspath(directory)
    self.pattern = pattern
    self._next = int(start)
    _check_output(os.path.join(self.directory, pattern % self._next))
    self.num_frames = 0
    self.paths: list[str] = []

  def __enter__(self) -> PngFrameWriter:
    return self

  def __exit__(self, exc_type, exc, tb) -> None:
    self.close()

  def append(self, frame) -> str:
    """Writes the next frame; returns its path."""
    path = os.path.join(self.directory, self.pattern % self._next)
    img = to_uint8(frame, f'{path}')
    save_png(path, img)  # creates the folder
    self._next += 1
    self.num_frames += 1
    self.paths.append(path)
    return path

  def close(self) -> None:
    """Nothing to flush (each PNG is complete when written)."""


def write_png_frames(directory: PathLike, frames,
                     pattern: str = PNG_PATTERN) -> list[str]:
  """Writes (T, H, W, 3) frames as ``directory/frame_%04d.png``.

  Returns:
    The paths written, in order.
  """
  frames = _frames_array(frames, os.fspath(directory))
  with PngFrameWriter(directory, pattern) as w:
    for f in frames:
      w.append(f)
  return w.paths


def save_space_time_slice(path: PathLike, slice_image, *,
                          time_scale: int = 1, time_axis: int = 0
                          ) -> np.ndarray:
  """Writes a space-time slice (PhysDreamer's figure) as PNG.

  Args:
    path: output PNG.
    slice_image: the slice, from
      :func:`physsplat_jax.render.slices.space_time_slice` (float in [0, 1]
      or uint8).
    time_scale: integer repeat of each frame's line along ``time_axis``
      (makes short videos visible).
    time_axis: the slice's time axis (as given to ``space_time_slice``).

  Returns:
    The image as written, uint8.
  """
  if int(time_scale) < 1:
    raise VideoError(f'time_scale must be >= 1, got {time_scale}')
  s = np.asarray(slice_image)
  if s.dtype == np.uint8:
    s = s.astype(np.float32) / 255.0
  s = np.repeat(s, int(time_scale), axis=time_axis)
  img = to_uint8(s, os.fspath(path))
  save_png(path, img)
  return img
