"""Outputs when the file system misbehaves: a full disk, a writer that fails
half-way, a rerun that fails, two runs into one folder."""

import collections
import errno
import json
import os
import shutil
import socket
import stat
import subprocess
import sys
import tempfile
import threading
from unittest import mock

import jax
import numpy as np
from absl.testing import absltest

from physsplat_jax import atomic_files
from physsplat_jax import pipeline as pl
from physsplat_jax.io import outputs
from physsplat_jax.io import paths
from physsplat_jax.io import video
from physsplat_jax.types import Gaussians

_FULL = OSError(errno.ENOSPC, 'No space left on device')


def _tmpdir(test) -> str:
  d = tempfile.TemporaryDirectory()
  test.addCleanup(d.cleanup)
  return d.name


def _hidden(folder: str) -> list[str]:
  return sorted(f for f in os.listdir(folder) if f.startswith('.'))


class AtomicWriteTest(absltest.TestCase):

  def test_a_full_disk_keeps_the_earlier_file_and_names_this_one(self):
    d = _tmpdir(self)
    path = os.path.join(d, 'report.json')
    outputs.write_json(path, {'run': 1})

    def half_then_full(tmp):
      with open(tmp, 'w') as f:
        f.write('{"run": ')
      raise _FULL

    with self.assertRaisesRegex(
        outputs.OutputError, r'report\.json: cannot write the JSON file \(No '
        r'space left on device: free space on that disk'):
      paths.write_atomically(path, half_then_full, outputs.OutputError,
                             what='JSON')
    self.assertEqual(json.load(open(path)), {'run': 1})
    self.assertEqual(_hidden(d), [])  # no temporary file left

  def test_an_input_error_inside_the_write_is_not_called_a_write_error(self):
    # Any OSError in the block was 'cannot write the ... file', even a
    # missing input the writer reads.
    d = _tmpdir(self)
    path = os.path.join(d, 'out.json')
    missing = os.path.join(d, 'input.npz')

    def reads_an_input(tmp):
      with open(tmp, 'w') as f:
        f.write('{')
      open(missing, 'rb')

    with self.assertRaises(FileNotFoundError) as cm:
      paths.write_atomically(path, reads_an_input, outputs.OutputError)
    self.assertNotIsInstance(cm.exception, outputs.OutputError)
    self.assertEqual(cm.exception.filename, missing)
    self.assertFalse(os.path.exists(path))
    self.assertEqual(_hidden(d), [])  # the temporary file removed

  def test_library_ply_writers_are_whole_or_not_at_all(self):
    # io.save_ply / save_scene / save_splat wrote into the file itself: a
    # full disk left half a PLY and a bare '[Errno 28]'.
    from physsplat_jax.io import ply
    from physsplat_jax.io import ply_format
    from physsplat_jax.test_util import random_gaussians
    d = _tmpdir(self)
    path = os.path.join(d, 'scene.ply')
    g = random_gaussians(jax.random.key(0), 8)
    ply.save_ply(path, g, binary=False)
    before = open(path, 'rb').read()
    with mock.patch.object(ply_format, '_format_ascii', side_effect=_FULL):
      with self.assertRaisesRegex(
          ply_format.PlyError, r'scene\.ply: cannot write the PLY file \(No '
          r'space left on device: free space on that disk'):
        ply.save_ply(path, random_gaussians(jax.random.key(1), 9),
                     binary=False)
    self.assertEqual(open(path, 'rb').read(), before)
    self.assertEqual(_hidden(d), [])

  def test_trajectory_png_and_json_writers_on_a_full_disk(self):
    d = _tmpdir(self)
    traj = outputs.TrajectoryOutput(os.path.join(d, 'trajectory.npz'), [0])
    traj.write(outputs.Frame(index=0, time=0.0, positions=np.zeros((1, 3))))
    with mock.patch.object(np, 'savez', side_effect=_FULL):
      with self.assertRaisesRegex(outputs.OutputError,
                                  r'trajectory\.npz: cannot write.*free space'):
        traj.close()
    png = os.path.join(d, 'frame.png')
    video.save_png(png, np.zeros((4, 4, 3)))
    before = open(png, 'rb').read()
    from PIL import Image  # noqa: PLC0415

    def fail_half_way(self_img, fp, *args, **kwargs):
      with open(fp, 'wb') as f:
        f.write(b'\x89PNG')
      raise _FULL

    with mock.patch.object(Image.Image, 'save', fail_half_way):
      with self.assertRaisesRegex(video.VideoError,
                                  r'frame\.png: cannot write the PNG file'):
        video.save_png(png, np.ones((4, 4, 3)))
    # The earlier PNG is whole (it was truncated to 0 bytes before).
    self.assertEqual(open(png, 'rb').read(), before)
    self.assertEqual(_hidden(d), [])

  def test_partial_names_are_per_write(self):
    # Per process only, two threads (or two hosts with equal pids on one
    # shared folder) writing one path shared a temporary file.
    p, q = (paths.partial_path('/x/video.mp4') for _ in range(2))
    self.assertRegex(p, rf'^/x/\.video\.{os.getpid()}-[0-9a-f]+\.partial'
                     r'\.mp4$')
    self.assertNotEqual(p, q)
    self.assertTrue(paths.PARTIAL.fullmatch(os.path.basename(p)))
    self.assertTrue(paths.PARTIAL.fullmatch('.video.123.partial.mp4'))
    self.assertFalse(paths.PARTIAL.fullmatch('video.mp4'))

  def test_links_pipes_and_extensionless_npz(self):
    d = _tmpdir(self)
    # A symbolic link: the file it points to is replaced, the link stays
    # (the rename put a plain file in the link's place).
    real = os.path.join(d, 'real.json')
    outputs.write_json(real, {'run': 1})
    os.chmod(real, 0o600)
    link = os.path.join(d, 'link.json')
    os.symlink(real, link)
    outputs.write_json(link, {'run': 2})
    self.assertTrue(os.path.islink(link))
    self.assertEqual(json.load(open(real)), {'run': 2})
    self.assertEqual(stat.S_IMODE(os.stat(real).st_mode), 0o600)
    # A named pipe (or /dev/stdout) is written directly, not replaced.
    fifo = os.path.join(d, 'pipe')
    os.mkfifo(fifo)
    got = []
    reader = threading.Thread(target=lambda: got.append(open(fifo).read()))
    reader.start()
    outputs.write_json(fifo, {'run': 3})
    reader.join(10)
    self.assertEqual(json.loads(got[0]), {'run': 3})
    self.assertTrue(stat.S_ISFIFO(os.stat(fifo).st_mode))
    # np.savez given a name adds '.npz' when it lacks one: the rename then
    # failed and the temporary file stayed.
    traj = outputs.TrajectoryOutput(os.path.join(d, 'traj'), [0])
    traj.write(outputs.Frame(index=0, time=0.0, positions=np.zeros((1, 3))))
    traj.close()
    self.assertEqual(np.load(os.path.join(d, 'traj'))['x'].shape,
                     (1, 1, 3))
    self.assertEqual(_hidden(d), [])


class VideoFailureTest(absltest.TestCase):

  def test_an_encoder_that_dies_leaves_no_file_and_no_second_error(self):
    d = _tmpdir(self)
    fake = os.path.join(d, 'ffmpeg')
    with open(fake, 'w') as f:
      f.write('#!/bin/sh\nhead -c 3000 > /dev/null\n'
              'echo "simulated encoder crash" >&2\nexit 1\n')
    os.chmod(fake, os.stat(fake).st_mode | stat.S_IEXEC)
    with mock.patch.dict(os.environ, {'IMAGEIO_FFMPEG_EXE': fake}):
      out = outputs.VideoOutput(os.path.join(d, 'video.mp4'), fps=10)
      frame = np.full((64, 64, 3), 0.5)
      with self.assertRaisesRegex(video.VideoError,
                                  'simulated encoder crash'):
        for i in range(50):
          out.write(outputs.Frame(index=i, time=0.0, image=frame))
      # Closing after that is quiet (it raised a FileNotFoundError of the
      # rename, which hid the encoder's reason) and writes nothing.
      self.assertEqual(out.close(), {})
    self.assertEqual(sorted(os.listdir(d)), ['ffmpeg'])

  def test_close_after_failure_logs_the_second_error(self):

    class Broken:
      def write(self, frame):
        pass

      def close(self):
        raise FileNotFoundError('the rename')

    with self.assertLogs(level='ERROR') as logs:
      outputs.close_after_failure(Broken())
    self.assertIn('FileNotFoundError: the rename', logs.output[0])


class RerunTest(absltest.TestCase):

  def test_a_run_that_writes_no_frame_keeps_the_earlier_frames(self):
    d = _tmpdir(self)
    frames, ply = os.path.join(d, 'frames'), os.path.join(d, 'ply')
    spz = os.path.join(d, 'spz')
    for folder, name in ((frames, 'frame_0000.png'), (ply, 'frame_0000.ply'),
                         (spz, 'frame_0000.spz')):
      os.makedirs(folder)
      with open(os.path.join(folder, name), 'w') as f:
        f.write('earlier run')
    # Creating the writers cleared the folders; a run failing after that
    # (a later output's check, the compile) lost the earlier run's frames.
    png_out = outputs.PngOutput(frames)
    ply_out = outputs.PlyOutput(ply, None)
    spz_out = outputs.SpzOutput(spz, None)
    self.assertEqual((png_out.close(), ply_out.close(), spz_out.close()),
                     ({}, {}, {}))
    self.assertEqual(os.listdir(frames), ['frame_0000.png'])
    self.assertEqual(os.listdir(ply), ['frame_0000.ply'])
    self.assertEqual(os.listdir(spz), ['frame_0000.spz'])

  def test_spz_frames_warn_of_clamped_values_once(self):
    """A colour beyond the .spz range clamps in every frame: one warning
    for the run, not one a frame; scales squashed below its range in a
    later frame warn then, once."""
    d = os.path.join(_tmpdir(self), 'spz')
    k = 4
    g = Gaussians(means=np.zeros((k, 3), np.float32),
                  log_scales=np.full((k, 3), -3.0, np.float32),
                  quats=np.tile(np.float32([1, 0, 0, 0]), (k, 1)),
                  opacity_logits=np.zeros(k, np.float32),
                  sh=np.full((k, 1, 3), 5.0, np.float32))  # > 3.33
    out = outputs.SpzOutput(d, g)
    cov = np.tile(np.eye(3, dtype=np.float32) * np.exp(-6.0), (k, 1, 1))
    tiny = cov * np.exp(-16.0)  # log-scales -11 < -10
    with self.assertLogs(level='WARNING') as logs:
      for i, c in enumerate((cov, cov, tiny, tiny)):
        out.write(outputs.Frame(index=i, time=0.0, gaussians=g.replace(
          means=g.means + 0.01 * i), covariances=c))
    warned = [m for m in logs.output if 'clamped' in m]
    self.assertLen(warned, 2)
    self.assertIn('frame_0000.spz', warned[0])
    self.assertIn('f_dc: 4', warned[0])
    self.assertIn('frame_0002.spz', warned[1])
    self.assertIn('log_scales: 4', warned[1])
    self.assertNotIn('f_dc', warned[1])
    self.assertLen(os.listdir(d), 4)


class FreeSpaceTest(absltest.TestCase):

  def test_a_warning_when_the_outputs_will_not_fit(self):
    d = _tmpdir(self)
    Usage = collections.namedtuple('Usage', 'total used free')
    need = {'trajectory': 3e6, 'frames': 5e8, 'video': 0.0}
    with mock.patch.object(atomic_files.shutil, 'disk_usage',
                           return_value=Usage(1e9, 9.9e8, 1e7)):
      with self.assertLogs(level='WARNING') as logs:
        self.assertFalse(outputs.check_free_space(d, need))
    self.assertIn('will write about 479.7 MB (trajectory 2.9 MB, frames '
                  '476.8 MB) and its disk has 9.5 MB free', logs.output[0])
    self.assertTrue(outputs.check_free_space(d, {'trajectory': 1.0}))


class CompileCacheTest(absltest.TestCase):

  def test_a_folder_that_takes_no_file_is_one_warning_and_no_cache(self):
    from physsplat_jax import compile_cache  # noqa: PLC0415
    d = _tmpdir(self)
    before = jax_cache_dir()
    # (a full disk: JAX warned once per program, 23 times in a small run)
    with mock.patch.object(compile_cache.tempfile, 'NamedTemporaryFile',
                           side_effect=_FULL):
      with self.assertLogs(level='WARNING') as logs:
        self.assertIsNone(compile_cache.enable_compilation_cache(d))
    self.assertLen(logs.output, 1)
    self.assertIn(f'cannot write to {d} (No space left on device); running '
                  'without it', logs.output[0])
    self.assertEqual(jax_cache_dir(), before)

  def test_the_suite_keeps_its_scripts_out_of_the_users_cache(self):
    # tests/conftest.py gives the scripts the tests run a folder of the
    # session's own (under the temporary folder, not ~/.cache).
    import conftest  # noqa: PLC0415
    from physsplat_jax import compile_cache  # noqa: PLC0415
    self.assertEqual(conftest.CACHE_ENV, compile_cache.ENV)
    folder = compile_cache.default_cache_dir()
    if folder != os.environ.get(conftest.OWN_CACHE):
      return  # the caller set PHYSSPLAT_JAX_CACHE: theirs
    self.assertTrue(folder.startswith(tempfile.gettempdir()), folder)
    self.assertIn('physsplat_tests_cache_', folder)
    self.assertTrue(os.path.isdir(folder))


def jax_cache_dir():
  import jax  # noqa: PLC0415
  return jax.config.jax_compilation_cache_dir


class LockTest(absltest.TestCase):

  def _lock(self, d, pid):
    with open(os.path.join(d, outputs._LOCK), 'w') as f:
      f.write(f'{pid} {socket.gethostname()}\n')

  def _holder(self, d):
    """Another process that holds ``d`` until killed."""
    other = subprocess.Popen(
      [sys.executable, '-c',
       'import sys, time\n'
       'from physsplat_jax.io import outputs\n'
       f'with outputs.output_lock({d!r}):\n'
       '  print("held", flush=True)\n'
       '  time.sleep(60)\n'], stdout=subprocess.PIPE, text=True,
      cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    self.addCleanup(other.wait)
    self.addCleanup(other.kill)
    self.assertEqual(other.stdout.readline().strip(), 'held')
    return other

  def test_one_run_per_folder(self):
    d = _tmpdir(self)
    other = self._holder(d)
    with self.assertRaisesRegex(
        outputs.OutputError, rf'in use by another run \(pid {other.pid} on '
        r'.*give another --out, or wait for that run to end'):
      with outputs.output_lock(d):
        pass
    # The other run ends (killed: its lock file stays): the next run takes
    # it over, and removes the temporary files it left.
    other.kill()
    other.wait()
    self.assertTrue(os.path.exists(os.path.join(d, outputs._LOCK)))
    for name in ('.video.123.partial.mp4', '.trajectory.123-0a1b.partial.npz',
                 'notes.txt'):
      open(os.path.join(d, name), 'w').close()
    with outputs.output_lock(d):
      with outputs.output_lock(d):  # nested in one thread: allowed
        owner = open(os.path.join(d, outputs._LOCK)).read().split()
        self.assertEqual(int(owner[0]), os.getpid())
      self.assertTrue(os.path.exists(os.path.join(d, outputs._LOCK)))
      self.assertEqual(sorted(os.listdir(d)),
                       [outputs._LOCK, 'notes.txt'])
    self.assertEqual(os.listdir(d), ['notes.txt'])
    # A lock file whose pid lives but holds no lock (a stale file whose pid
    # was reused; this process's own, left by an interrupted hold) is free.
    self._lock(d, os.getpid())
    with outputs.output_lock(d):
      pass
    # Released after an error too.
    with self.assertRaisesRegex(ValueError, 'boom'):
      with outputs.output_lock(d):
        raise ValueError('boom')
    self.assertEqual(os.listdir(d), ['notes.txt'])

  def test_runs_starting_at_once_get_one_hold(self):
    # A dead owner's lock file read by two runs at once: each removed it
    # and made its own, so both held the folder.
    d = _tmpdir(self)
    self._lock(d, 999999)
    n, start = 6, threading.Barrier(6)
    results = collections.Counter()
    tried = threading.Condition()

    def count(what):
      with tried:
        results[what] += 1
        tried.notify_all()

    def run():
      start.wait()
      try:
        with outputs.output_lock(d):
          count('held')
          with tried:  # held until every run has tried
            tried.wait_for(lambda: sum(results.values()) == n, timeout=10)
      except outputs.OutputError:
        count('refused')

    threads = [threading.Thread(target=run) for _ in range(n)]
    for t in threads:
      t.start()
    for t in threads:
      t.join(20)
    self.assertEqual(results, {'held': 1, 'refused': n - 1})
    self.assertEqual(os.listdir(d), [])

  def test_a_lock_file_that_cannot_be_written_is_not_left(self):
    d = _tmpdir(self)
    with mock.patch.object(atomic_files, '_write_owner', side_effect=_FULL):
      with self.assertRaisesRegex(
          outputs.OutputError, r'cannot write its lock file .*No space left'):
        with outputs.output_lock(d):
          pass
    self.assertEqual(os.listdir(d), [])
    with outputs.output_lock(d):  # and the next run is not refused
      pass

  def test_simulate_scene_refuses_a_held_folder_and_a_report_folder(self):
    d = _tmpdir(self)
    cfg = pl.PipelineConfig(num_frames=1, grid_res=16, max_particles=100,
                            use_mpdp=False, fill=False, render='none')
    os.mkdir(os.path.join(d, 'report.json'))
    # A folder in the report's place failed after the whole run.
    with self.assertRaisesRegex(outputs.OutputError,
                                r'report\.json: is a directory'):
      pl.simulate_scene(None, cfg, d)
    os.rmdir(os.path.join(d, 'report.json'))
    self._holder(d)
    with self.assertRaisesRegex(outputs.OutputError, 'in use by another run'):
      pl.simulate_scene(None, cfg, d)


def _raised(fn, *args):
  try:
    fn(*args)
  except Exception as e:  # noqa: BLE001 - returned for the test to check
    return e
  return None


class TrainingOutputsTest(absltest.TestCase):
  """Checkpoints, metrics and exported weights on a full disk: orbax's
  TensorStore traceback (and its worker threads' tracebacks after it)
  became one error naming the folder, the fix and the step to resume."""

  def setUp(self):
    super().setUp()
    from experiments.configs import mpdp_test
    from physsplat_jax.mpdp import train
    self.config = mpdp_test.get_config()
    self.train = train

  def test_no_room_stops_before_the_save_and_keeps_the_last_checkpoint(self):
    w = _tmpdir(self)
    ckpt = os.path.join(w, 'checkpoints')
    real = atomic_files.shutil.disk_usage

    def full_after_step_2(path):  # room for checkpoint 2, not for 4
      usage = real(path)
      if os.path.isdir(os.path.join(ckpt, '2')):
        return usage._replace(free=1000)
      return usage

    with mock.patch.object(atomic_files.shutil, 'disk_usage',
                           full_after_step_2):
      with self.assertRaisesRegex(
          self.train.MPDPError,
          r'checkpoints: no room for checkpoint 4: 0\.00 MB free on that '
          r'disk, a checkpoint needs about 0\.\d\d MB \(free space there, or '
          r'train in another --workdir\); the checkpoints written before '
          r'are kept: a rerun with the same --workdir resumes from step 2'):
        self.train.train_and_evaluate(self.config, w)
    self.assertEqual(sorted(os.listdir(ckpt)), ['2'])
    self.assertEqual(self.train.train_and_evaluate(self.config, w)['step'],
                     4)

  def test_a_full_disk_before_any_step_is_refused_up_front(self):
    w = _tmpdir(self)
    usage = collections.namedtuple('usage', 'total used free')
    with mock.patch.object(atomic_files.shutil, 'disk_usage',
                           return_value=usage(10**9, 10**9, 0)):
      with self.assertRaisesRegex(
          self.train.MPDPError, r'no room for the next checkpoint: .*no '
          r'checkpoint was written yet: a rerun starts from step 0'):
        self.train.train_and_evaluate(self.config, w)
    self.assertFalse(os.path.exists(os.path.join(w, 'metrics.jsonl')))

  def test_orbax_write_errors_are_named(self):
    # TensorStore's error text carries the OS error; orbax raised it as a
    # ValueError from the save (or, saving asynchronously, from a later
    # call).
    w = _tmpdir(self)
    ckpt = os.path.join(w, 'checkpoints')
    # (orbax 0.12's text on a full tmpfs, the array's key quoted first)
    tensorstore = ValueError(
      'RESOURCE_EXHAUSTED: Error writing "opt_state.1.0.nu.Dense_0.bias/0" '
      f'in OCDBT database at local file "{ckpt}/2.orbax-checkpoint-tmp/'
      'default.orbax-checkpoint-tmp/ocdbt.process_0/": Failed writing: "'
      f'{ckpt}/2.orbax-checkpoint-tmp/default.orbax-checkpoint-tmp/ocdbt.'
      'process_0/d/1f2e": Failed to write 4096 bytes to file 5: No space '
      "left on device [os_error_code='28']")
    with mock.patch('orbax.checkpoint.CheckpointManager.save',
                    side_effect=tensorstore):
      with self.assertRaisesRegex(
          self.train.MPDPError,
          r'checkpoints: cannot write checkpoint 2 \(No space left on '
          r'device: free space on that disk, or write the output '
          r'elsewhere\); no checkpoint was written yet'):
        self.train.train_and_evaluate(self.config, w)
    # metrics.jsonl: the file is named (Python's error on close had none).
    os.remove(os.path.join(w, 'metrics.jsonl'))
    os.mkdir(os.path.join(w, 'metrics.jsonl'))
    with self.assertRaisesRegex(
        self.train.MPDPError, r'metrics\.jsonl: cannot write the file'):
      self.train.append_metrics(w, {'step': 1})
    # Other errors pass as they are, also one raised while handling an OS
    # error (it was named as a write failure).
    with self.assertRaisesRegex(KeyError, 'other'):
      with self.train.checkpoint_manager(w, 2):
        try:
          open(os.path.join(w, 'missing'))
        except FileNotFoundError:
          raise KeyError('other') from None

  def test_one_training_per_workdir(self):
    # Two trainings into one workdir (a job submitted twice) wrote the same
    # checkpoints; the second now stops at once, naming the first.
    w = _tmpdir(self)
    with atomic_files.hold_folder(w, self.train.MPDPError, what='workdir',
                                  flag='--workdir'):
      errors = []
      other = threading.Thread(target=lambda: errors.append(
        _raised(self.train.train_and_evaluate, self.config, w)))
      other.start()
      other.join(60)
    self.assertRegex(str(errors[0]), r"workdir '.*' is in use by another "
                     r'run \(pid \d+ on .*\); give another --workdir')
    self.assertFalse(os.path.exists(os.path.join(w, 'checkpoints')))
    self.assertEqual(self.train.train_and_evaluate(self.config, w)['step'],
                     4)  # free again

  def test_exported_weights_are_written_whole_or_not_at_all(self):
    import jax
    from physsplat_jax.mpdp import model as model_lib
    from physsplat_jax.mpdp import pretrained
    d = _tmpdir(self)
    mcfg = model_lib.ModelConfig.from_dict(self.config.model.to_dict())
    params = model_lib.init_params(jax.random.key(0), mcfg)
    pretrained.save_params(params, mcfg, d, metadata={'run': 1})

    def files():
      return {f: open(os.path.join(d, f), 'rb').read()
              for f in os.listdir(d)}

    before = files()
    real = pretrained.atomic_files.write_atomically
    for failing in ('.npz', '.json'):  # either file: neither is replaced

      def full(path, write, error, what, failing=failing):
        if path.endswith(failing):
          write = mock.Mock(side_effect=_FULL)
        return real(path, write, error, what=what)

      with mock.patch.object(pretrained.atomic_files, 'write_atomically',
                             full):
        with self.assertRaisesRegex(
            model_lib.MPDPError, rf'mpdp_params\{failing}: cannot write the '
            r'weights file \(No space left on device: free space'):
          pretrained.save_params(params, mcfg, d, metadata={'run': 2})
      self.assertEqual(files(), before)
    self.assertEqual(pretrained.load_params(d)[2], {'run': 1})
    # A pair put together from two exports of one architecture loaded
    # silently: the description holds the weights' digest.
    other = _tmpdir(self)
    pretrained.save_params(jax.tree.map(lambda a: a + 1.0, params), mcfg,
                           other)
    shutil.copy(os.path.join(other, 'mpdp_params.npz'), d)
    with self.assertRaisesRegex(
        model_lib.MPDPError, r'mpdp_params\.npz: not the weights that '
        r'.*mpdp_params\.json describes \(their SHA-256 differs'):
      pretrained.load_params(d)


if __name__ == '__main__':
  absltest.main()
