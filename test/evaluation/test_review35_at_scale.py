"""Review 35: long ``cva-evaluate`` / ``cva-table1`` runs — records written after every scene,
``--resume`` / ``--reuse`` continuing an interrupted run, SIGTERM, progress with the time left."""

from __future__ import annotations

import json
import os
from pathlib import Path
import signal
import subprocess
import sys

import cv2
import numpy as np
import pytest

from cva_confidence_ros.datasets.synthetic import synthetic_pair
from cva_confidence_ros.evaluation import scene as scene_module
from cva_confidence_ros.evaluation.cli import main as evaluate

D = 16


def _folder(root: Path, count: int) -> Path:
    """``count`` tiny stereo_folder scenes s0, s1, ... (40×64, D = 16)."""
    for number in range(count):
        pair = synthetic_pair(500 + number, 40, 64, D)
        folder = root / f's{number}'
        folder.mkdir(parents=True)
        for name, image in (('left.png', pair.left), ('right.png', pair.right)):
            cv2.imwrite(str(folder / name),
                        cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image)
        np.save(folder / 'disparity.npy',
                np.where(np.isfinite(pair.disparity), pair.disparity, 0.0).astype(np.float32))
    return root


def _args(root: Path, records: Path, *more: str) -> list[str]:
    return ['--data-root', str(root), '--dataset', 'stereo_folder', '--matchers', 'census_bm',
            '--methods', 'pkrn,mlm', '--max-disparity', str(D), '--max-pixels', '300',
            '--json', str(records), *more]


def _failing_on(monkeypatch, call: int, error: BaseException) -> list[int]:
    """Make the ``call``-th ``evaluate_scene`` raise ``error``; returns the call log."""
    real = scene_module.evaluate_scene
    calls: list[int] = []

    def wrapped(sample, *args, **kwargs):
        calls.append(1)
        if len(calls) == call:
            raise error
        return real(sample, *args, **kwargs)

    monkeypatch.setattr(scene_module, 'evaluate_scene', wrapped)
    return calls


def test_a_crash_in_a_late_scene_keeps_the_records_of_the_scenes_before(tmp_path, monkeypatch):
    root = _folder(tmp_path / 'data', 4)
    records = tmp_path / 'r.json'
    _failing_on(monkeypatch, 3, RuntimeError('a fault no one expected'))
    with pytest.raises(RuntimeError, match='no one expected'):
        evaluate(_args(root, records))
    # Written only at the end before: the two scenes done were lost with the process.
    assert sorted({r['scene'] for r in json.loads(records.read_text())}) == ['s0', 's1']


def test_resume_scores_only_the_rest_and_ends_as_an_uninterrupted_run(
    tmp_path, monkeypatch, capsys
):
    root = _folder(tmp_path / 'data', 4)
    full, records = tmp_path / 'full.json', tmp_path / 'r.json'
    assert evaluate(_args(root, full)) == 0
    calls = _failing_on(monkeypatch, 4, KeyboardInterrupt())
    assert evaluate(_args(root, records)) == 130
    assert len(json.loads(records.read_text())) == 6  # 3 scenes × 2 methods
    calls.clear()
    capsys.readouterr()
    assert evaluate(_args(root, records, '--resume')) == 0
    err = capsys.readouterr().err
    # s0 scored again to check the file, s1 and s2 taken over, s3 scored.
    assert len(calls) == 2
    assert '[2/4] stereo_folder/s1 taken over' in err and '[3/4] stereo_folder/s2 taken' in err
    assert records.read_bytes() == full.read_bytes()


def test_resume_refuses_a_file_of_other_settings_and_leaves_it_alone(tmp_path, capsys):
    root = _folder(tmp_path / 'data', 2)
    records = tmp_path / 'r.json'
    assert evaluate(_args(root, records)) == 0
    before = records.read_bytes()
    more = _args(root, records, '--resume')
    more[more.index('--max-pixels') + 1] = '200'
    capsys.readouterr()
    assert evaluate(more) == 2
    last = capsys.readouterr().err.splitlines()[-1]
    assert last.startswith(f'cva-evaluate: error: --resume: {records} was written with other')
    assert 'n_pixels 300 there' in last and 'n_pixels 200 now' in last
    assert records.read_bytes() == before
    # Records of a method this run does not score would be dropped from the file.
    fewer = _args(root, records, '--resume')
    fewer[fewer.index('--methods') + 1] = 'pkrn'
    assert evaluate(fewer) == 2
    assert 'stereo_folder/s0 census_bm mlm, which this run does not score' in (
        capsys.readouterr().err)
    assert records.read_bytes() == before


def test_progress_gives_the_time_so_far_and_left(tmp_path, capsys):
    root = _folder(tmp_path / 'data', 2)
    assert evaluate(_args(root, tmp_path / 'r.json')) == 0
    err = capsys.readouterr().err
    assert '[1/2] stereo_folder/s0 done; 0:00:0' in err and 'left' in err


_SIGTERM_ON_THE_SECOND_SCENE = """
import os, signal, sys
from cva_confidence_ros.evaluation import scene
from cva_confidence_ros.evaluation.cli import main
real, calls = scene.evaluate_scene, []
def wrapped(*args, **kwargs):
    calls.append(1)
    if len(calls) == 2:
        os.kill(os.getpid(), signal.SIGTERM)
    return real(*args, **kwargs)
scene.evaluate_scene = wrapped
sys.exit(main(sys.argv[1:]))
"""


def test_sigterm_ends_like_ctrl_c_with_the_scenes_done_written(tmp_path):
    root = _folder(tmp_path / 'data', 3)
    records, out = tmp_path / 'r.json', tmp_path / 'out'
    done = subprocess.run(
        [sys.executable, '-c', _SIGTERM_ON_THE_SECOND_SCENE,
         *_args(root, records, '--out', str(out))],
        capture_output=True, text=True, timeout=120, env={**os.environ, 'NUMBA_NUM_THREADS': '1'},
    )
    # Before: the default action, -15, nothing written.
    assert done.returncode == 128 + signal.SIGTERM, done.stderr[-2000:]
    assert 'interrupted after 1 of 3 scenes' in done.stderr
    assert {r['scene'] for r in json.loads(records.read_text())} == {'s0'}
    assert '**Partial: 1 of 3 scenes**' in (out / 'table.md').read_text()


def test_network_progress_bar_refreshes_rarely_in_a_log(monkeypatch, capsys):
    import tqdm

    seen: list[float] = []

    class Bar(tqdm.tqdm):
        def __init__(self, *args, **kwargs):
            seen.append(kwargs['mininterval'])
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(tqdm, 'tqdm', Bar)

    class Method:
        class evaluator:  # noqa: N801 (stands in for an object with a progress hook)
            progress = None

    with scene_module._network_progress(Method, 'census_bm cva_net', True):
        Method.evaluator.progress(1, 10)
    # stderr is captured, not a terminal: one refresh a minute, not a second.
    assert seen == [60.0]


def _middlebury(root: Path, scenes: int) -> Path:
    from cva_confidence_ros.datasets.io import write_pfm

    for number in range(scenes):
        folder = root / 'middlebury2014' / 'trainingQ' / f'S{number}'
        folder.mkdir(parents=True)
        pair = synthetic_pair(600 + number, 40, 64, D)
        for name, image in (('im0.png', pair.left), ('im1.png', pair.right)):
            cv2.imwrite(str(folder / name),
                        cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image)
        write_pfm(folder / 'disp0GT.pfm', np.where(np.isfinite(pair.disparity),
                                                   pair.disparity, np.inf).astype(np.float32))
    return root


@pytest.fixture
def _restore_threads():
    import numba
    import torch

    threads, numba_threads = torch.get_num_threads(), numba.get_num_threads()
    yield
    numba.set_num_threads(numba_threads)
    torch.set_num_threads(threads)


@pytest.mark.usefixtures('_restore_threads')
def test_table1_writes_after_every_scene_and_reuse_continues_it(tmp_path, monkeypatch):
    from cva_confidence_ros.evaluation.table1 import main as table1

    root = _middlebury(tmp_path / 'data', 3)
    out = tmp_path / 'out'
    base = ['--data-root', str(root), '--matchers', 'census_bm', '--methods', 'pkrn',
            '--max-disparity', str(D), '--max-pixels', '100', '--protocol', 'develop',
            '--threads', '1', '--out', str(out)]
    calls = _failing_on(monkeypatch, 3, RuntimeError('a fault no one expected'))
    with pytest.raises(RuntimeError):
        table1(base)
    summary = json.loads((out / 'table1.json').read_text())
    assert [r['scene'] for r in summary['records']] == ['S0', 'S1']
    assert summary['partial'] == 'in progress: 2 of 3 scenes done'
    monkeypatch.undo()
    calls = _failing_on(monkeypatch, 0, RuntimeError())  # count only
    assert table1([*base, '--reuse', str(out / 'table1.json')]) == 0
    # S0 scored again to check the file, S1 taken over, S2 scored; before, all three.
    assert len(calls) == 2
    summary = json.loads((out / 'table1.json').read_text())
    assert [(r['scene'], r.get('reused', False)) for r in summary['records']] == [
        ('S0', True), ('S1', True), ('S2', False)]
    assert summary['partial'] is None
