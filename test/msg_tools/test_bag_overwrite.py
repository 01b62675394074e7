"""``--overwrite`` of ``cva-bag-replay`` and ``cva-bag-from-dataset``: an earlier report is
refused or cleared, never mixed with a new one; an old output bag is replaced only by a bag
that holds something."""

from __future__ import annotations

import json
from pathlib import Path

from msg_test_utils import (
    MAX_DISPARITY,
    START_NS,
    dataset_bag,
    read_bag,
    synthetic_samples,
    write_stereo_bag,
)
import numpy as np
import pytest

from cva_confidence_ros.errors import BagError
from msg_tools.bag_from_dataset import main as from_dataset
from msg_tools.bag_from_dataset import write_dataset_bag
from msg_tools.bag_replay import main as replay
from msg_tools.bagio import OutputBag
from msg_tools.convert import IMAGE, image_to_msg, jazzy_typestore


def _replay(bag: Path, out: Path, report: Path, *extra: str) -> int:
    return replay([str(bag), '--out', str(out), '--report', str(report), '--max-disparity',
                   str(MAX_DISPARITY), '--confidence-method', 'pkrn', *extra])


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.rglob('*')) if p.is_file()}


def _unpairable_bag(path: Path) -> Path:
    """A bag whose right images are 2 ms off: no frame pairs, nothing is written."""
    return write_stereo_bag(path, [{'stamp_right': START_NS + i * 100_000_000 + 2_000_000}
                                   for i in range(2)])


def test_earlier_report_is_refused_without_overwrite(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}, {}, {}])
    report = tmp_path / 'report'
    assert _replay(bag, tmp_path / 'out1', report) == 0
    assert (report / 'confidence_00002.png').is_file()
    before = _files(report)
    capsys.readouterr()
    # Another output bag, the same report folder: refused before any work.
    assert _replay(bag, tmp_path / 'out2', report) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and 'Traceback' not in err
    assert err.startswith(f'cva-bag-replay: error: the report folder {report} holds an earlier '
                          f'report (')
    assert 'use --overwrite to replace it, or pick another folder' in err
    assert _files(report) == before and not (tmp_path / 'out2').exists()


def test_overwrite_replaces_the_whole_earlier_report(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    report = tmp_path / 'report'
    big = write_stereo_bag(tmp_path / 'big', [{}, {}, {}])
    assert _replay(big, tmp_path / 'out', report) == 0
    (report / 'notes.txt').write_text('mine\n')
    small = write_stereo_bag(tmp_path / 'small', [{'shift': 3}])
    assert _replay(small, tmp_path / 'out', report, '--overwrite') == 0
    names = {p.name for p in report.iterdir()}
    # Nothing of the three-frame run is left next to the one-frame report; the user's file is.
    assert names == {'report.json', 'report.csv', 'summary.md', 'auc_over_time.png',
                     'confidence_over_time.png', 'confidence_00000.png', 'roc_00000.png',
                     'overlay_00000.png', 'least_kept_00000.png', 'notes.txt'}
    assert (report / 'notes.txt').read_text() == 'mine\n'
    document = json.loads((report / 'report.json').read_text())
    assert document['config']['bag'] == str(small) and len(document['frames']) == 1
    assert len((report / 'report.csv').read_text().strip().splitlines()) == 2
    assert len(read_bag(tmp_path / 'out')['/disparity']) == 1


def test_folder_that_is_no_report_is_refused_even_with_overwrite(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}])
    folder = tmp_path / 'mine'
    folder.mkdir()
    (folder / 'thesis.tex').write_text('keep\n')
    (folder / 'roc_00000.png').write_bytes(b'not ours\n')
    for extra in ((), ('--overwrite',)):
        assert _replay(bag, tmp_path / 'out', folder, *extra) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1
        assert (f'the report folder {folder} is not empty and holds no cva-bag-replay report '
                f'(no report.json; it has roc_00000.png, thesis.tex); pick another folder') in err
        assert _files(folder) == {'roc_00000.png': b'not ours\n', 'thesis.tex': b'keep\n'}
        assert not (tmp_path / 'out').exists()


def test_bags_inside_the_report_folder_do_not_count(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = tmp_path / 'run'
    bag = write_stereo_bag(run / 'in', [{}])
    assert _replay(bag, run / 'out', run) == 0
    input_bytes = _files(bag)
    # Again, over its own report: the input and output bags in the folder are no report.
    assert _replay(bag, run / 'out', run, '--overwrite') == 0
    assert _files(bag) == input_bytes
    assert len(read_bag(run / 'out')['/disparity']) == 1
    assert {p.name for p in run.iterdir()} >= {'in', 'out', 'report.json'}
    assert not [p for p in run.iterdir() if p.name.startswith('.')]


def test_replay_keeps_the_old_bag_when_it_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    good = write_stereo_bag(tmp_path / 'good', [{}, {}])
    out = tmp_path / 'out'
    assert _replay(good, out, tmp_path / 'report') == 0
    before = _files(out)
    capsys.readouterr()
    assert _replay(_unpairable_bag(tmp_path / 'bad'), out, tmp_path / 'report',
                   '--overwrite') == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert 'no stereo pair matched by stamp' in line
    assert f'the existing output bag {out} was left as it was (nothing written)' in line
    assert _files(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ['bad', 'good', 'out', 'report']
    # A run that writes frames does replace it; the storage file is named after the bag.
    assert _replay(good, out, tmp_path / 'report', '--overwrite', '--storage', 'sqlite3') == 0
    assert (out / 'out.db3').is_file() and 'storage_identifier: sqlite3' in (
        out / 'metadata.yaml').read_text()
    assert len(read_bag(out)['/disparity']) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ['bad', 'good', 'out', 'report']


def test_existing_output_bag_is_refused_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}])
    (tmp_path / 'out').mkdir()
    (tmp_path / 'out' / 'metadata.yaml').write_text('old\n')
    assert _replay(bag, tmp_path / 'out', tmp_path / 'report') == 2
    err = capsys.readouterr().err
    assert err.strip() == (f'cva-bag-replay: error: output bag {tmp_path / "out"} exists '
                           f'already; use --overwrite to replace it, or pick another')
    assert not (tmp_path / 'report').exists()


def test_empty_input_bag(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from rosbags.rosbag2 import Writer

    empty = tmp_path / 'empty'
    writer = Writer(empty, version=8)
    writer.open()
    writer.close()
    assert _replay(empty, tmp_path / 'out', tmp_path / 'report') == 2
    err = capsys.readouterr().err
    assert err.strip() == f'cva-bag-replay: error: bag {empty} is empty (0 messages)'
    assert not (tmp_path / 'out').exists()


def test_from_dataset_keeps_the_old_bag_when_the_first_scene_is_broken(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = dataset_bag(tmp_path, 'mcap', 2)
    before = _files(bag)
    capsys.readouterr()
    (tmp_path / 'data' / 'trainingQ' / 'Scene0' / 'im0.png').write_bytes(b'')
    code = from_dataset(['--data-root', str(tmp_path / 'data'), '--dataset', 'middlebury2014',
                         '--out', str(bag), '--overwrite'])
    assert code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and 'Traceback' not in err
    assert 'im0.png' in err and f'the existing bag {bag} was left as it was' in err
    assert _files(bag) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ['data', bag.name]


def test_output_bag_replaced_only_when_written(tmp_path: Path) -> None:
    store = jazzy_typestore()
    message = image_to_msg(np.zeros((2, 3), np.uint8), START_NS, 'l', store)
    path = tmp_path / 'bag'
    with OutputBag(path) as bag:
        bag.write('/a', IMAGE, message, START_NS)
    old = _files(path)
    # Nothing written: the old bag stays, the staging folder goes.
    with OutputBag(path, overwrite=True) as bag:
        pass
    assert bag.kept_old and _files(path) == old
    # Stopped part-way (an exception, as a Ctrl-C is) after a message: the new bag replaces it.
    with pytest.raises(KeyboardInterrupt), OutputBag(path, 'sqlite3', overwrite=True) as bag:
        bag.write('/b', IMAGE, message, START_NS)
        raise KeyboardInterrupt
    assert not bag.kept_old and set(read_bag(path)) == {'/b'}
    assert (path / 'bag.db3').is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ['bag']
    with pytest.raises(BagError, match='exists already'):
        OutputBag(path).open()


def test_from_dataset_ctrl_c_after_a_frame_replaces_the_old_bag(tmp_path: Path) -> None:
    bag = dataset_bag(tmp_path, 'mcap', 2)
    [sample] = synthetic_samples(1, first_seed=11)

    def one_then_ctrl_c():  # noqa: ANN202  (a generator of samples)
        yield sample
        raise KeyboardInterrupt

    summary = write_dataset_bag(one_then_ctrl_c(), bag, overwrite=True, log=lambda _: None)
    assert summary.interrupted and summary.frames == 1 and not summary.kept_old
    messages = read_bag(bag)
    assert {len(rows) for rows in messages.values()} == {1}
    assert messages['/left/image_rect'][0][1].width == sample.left.shape[1]
    assert sorted(p.name for p in tmp_path.iterdir()) == ['data', bag.name]


@pytest.mark.parametrize('mode', ['offline', 'live'])
def test_an_output_bag_that_cannot_be_created_keeps_the_old_report(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], mode: str
) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}])
    report = tmp_path / 'report'
    assert _replay(bag, tmp_path / 'out', report) == 0
    before = _files(report)
    blocker = tmp_path / 'plain.txt'
    blocker.write_text('x')
    capsys.readouterr()
    assert _replay(bag, blocker / 'out', report, '--overwrite', '--mode', mode,
                   '--no-start-node', '--startup-timeout', '1') == 2
    assert capsys.readouterr().err.strip() == (
        f'cva-bag-replay: error: cannot create output bag {blocker / "out"}: {blocker} is a '
        f'file, not a folder'
    )
    assert _files(report) == before
    assert blocker.read_text() == 'x'


def test_an_output_folder_that_cannot_be_written_keeps_the_old_report(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import tempfile

    bag = write_stereo_bag(tmp_path / 'in', [{}])
    report = tmp_path / 'report'
    assert _replay(bag, tmp_path / 'out', report) == 0
    before = _files(report)
    locked = tmp_path / 'locked'
    real = tempfile.TemporaryFile

    def refuse(*args: object, **kwargs: object) -> object:
        # A read-only folder, also for root (who passes permission bits).
        if Path(str(kwargs.get('dir', ''))) == locked:
            raise PermissionError(13, 'Permission denied')
        return real(*args, **kwargs)

    monkeypatch.setattr(tempfile, 'TemporaryFile', refuse)
    capsys.readouterr()
    assert _replay(bag, locked / 'out', report, '--overwrite') == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f'cva-bag-replay: error: cannot create output bag {locked / "out"}: ')
    assert err.endswith(f'cannot write in {locked} (Permission denied)')
    assert _files(report) == before
