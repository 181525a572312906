"""Every command quoted in README.md and docs/ names a real script and flags.

Commands ``python -m experiments.NAME --flag=...`` are extracted from the
Markdown (backslash continuations joined); each NAME must be a script and
each flag one that the script defines (its own ``DEFINE_*`` calls, the
flags of what it imports, absl's), and ``--config.FIELD`` on the pipeline
scripts a field of their config file. Links between the Markdown files
(``[text](file.md#anchor)``, ``[text](#anchor)``) reach a real heading.
"""

import ast
import pathlib
import re
import shlex

from absl.testing import absltest

ROOT = pathlib.Path(__file__).resolve().parent.parent
SCRIPTS = ROOT / 'experiments'
# Flags defined by modules the scripts import (and absl's own).
SHARED = {
  'experiments/lib/cli.py': 'cli',
  'physsplat_jax/perception/flags.py': 'perception.define_flags',
  'physsplat_jax/io/mllm.py': 'perception.define_flags',
  'physsplat_jax/distributed/runtime.py': 'runtime.define_flags',
}
ABSL = {'help', 'helpfull', 'helpshort', 'helpxml', 'verbosity', 'v',
        'logtostderr', 'alsologtostderr', 'log_dir', 'flagfile'}


def _defined(path: pathlib.Path) -> set[str]:
  names = set()
  for node in ast.walk(ast.parse(path.read_text())):
    if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
        and (node.func.attr.startswith('DEFINE')
             or node.func.attr == 'define_config_file') and node.args
        and isinstance(node.args[0], ast.Constant)):
      names.add(node.args[0].value)
    # Tables of (flags.DEFINE_x, 'name', ...) rows.
    if (isinstance(node, ast.Tuple) and len(node.elts) >= 2
        and isinstance(node.elts[0], ast.Attribute)
        and node.elts[0].attr.startswith('DEFINE')
        and isinstance(node.elts[1], ast.Constant)):
      names.add(node.elts[1].value)
  return names


def _commands():
  for md in [ROOT / 'README.md', *sorted((ROOT / 'docs').glob('*.md'))]:
    text = md.read_text().replace('\\\n', ' ')
    for m in re.finditer(r'python -m experiments\.(\w+)([^`\n|]*)', text):
      yield md.name, m.group(1), m.group(2)


class DocsCommandsTest(absltest.TestCase):

  def test_commands_name_real_scripts_and_flags(self):
    shared = set(ABSL)
    for rel in SHARED:
      shared |= _defined(ROOT / rel)
    simulate_fields = set(re.findall(
      r'^  c\.(\w+) =', (SCRIPTS / 'configs' / 'simulate.py').read_text(),
      re.M))
    bad, seen = [], 0
    for doc, script, rest in _commands():
      path = SCRIPTS / f'{script}.py'
      if not path.exists():
        bad.append(f'{doc}: experiments.{script} does not exist')
        continue
      flags = _defined(path) | shared
      try:
        tokens = shlex.split(rest)
      except ValueError:
        tokens = rest.split()
      for tok in tokens:
        if not tok.startswith('--'):
          continue
        seen += 1
        name = tok[2:].split('=', 1)[0]
        if name.startswith('config.'):
          if (script in ('simulate', 'demo')
              and name.split('.')[1] not in simulate_fields):
            bad.append(f'{doc}: experiments.{script} {tok}: no such field')
          continue
        if name not in flags and not (name.startswith('no')
                                      and name[2:] in flags):
          bad.append(f'{doc}: experiments.{script} {tok}: no such flag')
    self.assertGreater(seen, 20)
    self.assertEqual(bad, [])

  def test_links_reach_real_headings(self):
    docs = [ROOT / 'README.md', *sorted((ROOT / 'docs').glob('*.md'))]

    def slug(heading):  # GitHub's anchors
      text = heading.lstrip('#').strip().lower()
      return re.sub(r'[^\w\- ]', '', text).replace(' ', '-')

    anchors = {md.resolve(): {slug(ln) for ln in md.read_text().splitlines()
                              if ln.startswith('#')} for md in docs}
    bad, seen = [], 0
    for md in docs:
      for m in re.finditer(r'\]\(([^)#\s]*)#([^)\s]+)\)', md.read_text()):
        target = (md.parent / m.group(1)).resolve() if m.group(1) else (
          md.resolve())
        if target not in anchors:
          continue
        seen += 1
        if m.group(2) not in anchors[target]:
          bad.append(f'{md.name}: {m.group(0)}')
    self.assertGreater(seen, 20)
    self.assertEqual(bad, [])


if __name__ == '__main__':
  absltest.main()
