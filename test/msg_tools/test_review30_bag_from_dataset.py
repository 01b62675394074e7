"""Review 30 of ``cva-bag-from-dataset`` and ``bagio``: what a failed run leaves at ``--out``,
ground-truth topics that clash with the camera topics, the assumed-calibration line."""

from __future__ import annotations

from collections.abc import Iterator
import dataclasses
from pathlib import Path
from typing import Any

from msg_test_utils import read_bag, synthetic_samples, write_middlebury_root
import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError, DataError
from msg_tools.bag_from_dataset import BagSpec, main, write_dataset_bag
from msg_tools.bagio import OutputBag
from msg_tools.convert import IMAGE, image_to_msg, jazzy_typestore


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.rglob('*')) if p.is_file()}


def _args(root: Path, out: Path, *extra: str) -> list[str]:
    return ['--data-root', str(root), '--dataset', 'middlebury2014', '--out', str(out), *extra]


def _break(root: Path, scene: int) -> None:
    (root / 'trainingQ' / f'Scene{scene}' / 'im1.png').write_bytes(b'junk')


def test_a_broken_first_scene_leaves_no_empty_bag(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = write_middlebury_root(tmp_path / 'data', synthetic_samples(1))
    _break(root, 0)
    out = tmp_path / 'bag'
    assert main(_args(root, out)) == 2
    err = capsys.readouterr().err
    assert 'im1.png' in err and f'no bag was written at {out}' in err
    assert len(err.strip().splitlines()) == 1
    # Before: an empty bag was left, and the retry was refused ('exists already').
    assert not out.exists()
    write_middlebury_root(root, synthetic_samples(1))
    assert main(_args(root, out)) == 0
    assert {len(rows) for rows in read_bag(out).values()} == {1}


def test_a_broken_later_scene_keeps_the_old_bag(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = write_middlebury_root(tmp_path / 'data', synthetic_samples(3))
    out = tmp_path / 'bag'
    assert main(_args(root, out)) == 0
    before = _files(out)
    capsys.readouterr()
    _break(root, 1)
    assert main(_args(root, out, '--overwrite')) == 2
    err = capsys.readouterr().err
    assert f'the existing bag {out} was left as it was (the 1 frames written were dropped)' in err
    # Before: the complete 3-frame bag was replaced by the 1 frame written before the error.
    assert _files(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ['bag', 'data']


def test_a_broken_later_scene_says_what_a_new_bag_holds(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = write_middlebury_root(tmp_path / 'data', synthetic_samples(3))
    _break(root, 2)
    out = tmp_path / 'bag'
    assert main(_args(root, out)) == 2
    err = capsys.readouterr().err
    assert f'{out} holds the 2 frames written before it' in err
    assert {len(rows) for rows in read_bag(out).values()} == {2}


def test_an_unexpected_error_replaces_no_old_bag(tmp_path: Path) -> None:
    first, second = synthetic_samples(2)
    out = tmp_path / 'bag'
    write_dataset_bag([first, second], out, log=lambda _: None)
    before = _files(out)

    def samples() -> Iterator[Any]:
        yield first
        raise MemoryError  # a scene too large to load

    with pytest.raises(MemoryError):
        write_dataset_bag(samples(), out, overwrite=True, log=lambda _: None)
    assert _files(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ['bag']


def test_output_bag_closed_as_failed(tmp_path: Path) -> None:
    store = jazzy_typestore()
    message = image_to_msg(np.zeros((2, 3), np.uint8), 5, 'l', store)
    path = tmp_path / 'bag'
    with OutputBag(path) as bag:
        bag.write('/old', IMAGE, message, 5)
    old = _files(path)
    staged = OutputBag(path, overwrite=True)
    staged.open()
    assert staged.replacing
    staged.write('/new', IMAGE, message, 5)
    staged.close(failed=True)
    assert staged.kept_old and _files(path) == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ['bag']
    empty = OutputBag(tmp_path / 'empty')
    empty.open()
    assert not empty.replacing
    empty.close(failed=True)
    assert empty.dropped_empty and not (tmp_path / 'empty').exists()
    partial = OutputBag(tmp_path / 'partial', 'sqlite3')
    partial.open()
    partial.write('/new', IMAGE, message, 5)
    partial.close(failed=True)
    assert not partial.dropped_empty and set(read_bag(tmp_path / 'partial')) == {'/new'}


@pytest.mark.parametrize(
    'gt_topic', ['left/image_rect', '/right/camera_info/', 'left/camera_info']
)
def test_a_ground_truth_topic_on_a_camera_topic_is_refused(
    tmp_path: Path, gt_topic: str
) -> None:
    # Before: accepted; the first frame's images and infos were written, then the ground
    # truth failed on the topic's type, leaving a frame without ground truth.
    with pytest.raises(ConfigError, match='is one of the image or camera-info topics'):
        BagSpec(gt_topic=gt_topic, topic_prefix='/stereo')
    assert BagSpec(gt_topic='left/disparity_gt').topic('left/disparity_gt')


@pytest.mark.parametrize(
    ('extra', 'said', 'not_said'),
    [
        ({'focal': 30.0}, 'assuming B = 0.1 m (set --baseline)', 'f = image width'),
        ({'baseline': 0.5}, 'assuming f = image width (set --focal)', 'B = 0.1 m'),
        ({}, 'assuming f = image width, B = 0.1 m (set --focal/--baseline)', None),
    ],
)
def test_the_assumed_calibration_names_only_what_was_assumed(
    tmp_path: Path, extra: dict[str, float], said: str, not_said: str | None
) -> None:
    sample = dataclasses.replace(synthetic_samples(1)[0], calib=None)
    lines: list[str] = []
    summary = write_dataset_bag([sample], tmp_path / 'bag', BagSpec(**extra), log=lines.append)
    assert summary.assumed_calibration
    [line] = [text for text in lines if 'has no calibration' in text]
    assert said in line
    if not_said is not None:
        assert not_said not in line  # before: 'f = image width, B = 0.1 m' whatever was set


def test_a_data_error_keeps_its_type(tmp_path: Path) -> None:
    def samples() -> Iterator[Any]:
        raise DataError('scene 0 is broken')
        yield

    with pytest.raises(DataError, match=r'^scene 0 is broken; no bag was written at '):
        write_dataset_bag(samples(), tmp_path / 'bag', log=lambda _: None)
    assert not (tmp_path / 'bag').exists()
