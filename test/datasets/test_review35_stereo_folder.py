"""``stereo_folder``: a user's own pairs with ground truth, one folder per scene, on tiny files.

The data set reads ``<scene>/left.png``, ``right.png`` and one of ``disparity.pfm`` (inf/NaN =
unknown), ``disparity.npy`` (0/NaN/inf = unknown) or ``disparity.png`` (16-bit KITTI, 0 =
unknown), with optional ``nonocc.png`` and ``calib.txt``, and works in every tool that takes a
registered data set name.
"""

from __future__ import annotations

from collections.abc import Iterator
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from cva_confidence_ros.datasets import (
    DATASETS,
    DEVELOP_DATASETS,
    TRAIN_DATASETS,
    list_scenes,
    load_dataset,
    load_scene,
    write_pfm,
)
from cva_confidence_ros.errors import ConfigError, DataError

NAME = 'stereo_folder'
H, W = 48, 64
CALIB = 'cam0=[100 0 30; 0 100 20; 0 0 1]\ncam1=[100 0 31.5; 0 100 20; 0 0 1]\n' \
    'doffs=1.5\nbaseline=120\nwidth=64\nheight=48\n'


def pair(disparity: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A textured (H, W, 3) pair with a constant disparity: left[y, x] = right[y, x - d]."""
    wide = np.random.default_rng(seed).integers(0, 256, (H, W + 16, 3), dtype=np.uint8)
    wide = cv2.GaussianBlur(wide, (3, 3), 0)
    left = np.ascontiguousarray(wide[:, 16 - disparity: 16 - disparity + W])
    right = np.ascontiguousarray(wide[:, 16: 16 + W])
    truth = np.full((H, W), float(disparity), np.float32)
    truth[:, :disparity] = np.nan  # no match in the right image
    return left, right, truth


def write_scene(
    folder: Path,
    disparity: int = 4,
    form: str = 'npy',
    seed: int = 0,
    suffix: str = '.png',
    grey: bool = False,
) -> np.ndarray:
    """Write one scene; the ground truth as ``form``; returns the expected disparity."""
    folder.mkdir(parents=True, exist_ok=True)
    left, right, truth = pair(disparity, seed)
    for side, image in (('left', left), ('right', right)):
        out = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if grey else image[..., ::-1]
        assert cv2.imwrite(str(folder / f'{side}{suffix}'), out)
    if form == 'npy':
        np.save(folder / 'disparity.npy', np.nan_to_num(truth, nan=0.0))
    elif form == 'pfm':
        write_pfm(folder / 'disparity.pfm', np.where(np.isnan(truth), np.inf, truth))
    else:
        stored = np.round(np.nan_to_num(truth) * 256).astype(np.uint16)
        assert cv2.imwrite(str(folder / 'disparity.png'), stored)
    return truth


def same(actual: np.ndarray, expected: np.ndarray) -> None:
    np.testing.assert_array_equal(np.isnan(actual), np.isnan(expected))
    np.testing.assert_allclose(actual[~np.isnan(actual)], expected[~np.isnan(expected)])


@pytest.fixture
def _restore_threads() -> Iterator[None]:
    """``--threads 1`` changes process-wide settings; give the other tests theirs back."""
    torch = pytest.importorskip('torch')
    import numba

    threads, numba_threads = torch.get_num_threads(), numba.get_num_threads()
    yield
    numba.set_num_threads(numba_threads)
    torch.set_num_threads(threads)


def test_registered_in_neither_split_and_trainable() -> None:
    from cva_confidence_ros.evaluation.cli import parse_dataset_names
    from cva_confidence_ros.training.config import check_training_datasets

    assert NAME in DATASETS
    assert NAME not in TRAIN_DATASETS and NAME not in DEVELOP_DATASETS
    assert check_training_datasets([NAME]) == [(NAME, None)]
    assert NAME not in parse_dataset_names('develop')
    assert parse_dataset_names(f'{NAME},kitti2015') == [NAME, 'kitti2015']
    with pytest.raises(ConfigError, match='has splits none'):
        list_scenes(NAME, '.', split='training')


def test_scenes_at_any_depth_and_the_root_itself(tmp_path: Path) -> None:
    write_scene(tmp_path / 'run2' / 'cam_front' / '000010', seed=1)
    write_scene(tmp_path / 'run1' / '000003', seed=2)
    write_scene(tmp_path / 'a', seed=3)
    (tmp_path / 'notes').mkdir()
    (tmp_path / 'incomplete').mkdir()  # a left image only: not a scene
    cv2.imwrite(str(tmp_path / 'incomplete' / 'left.png'), np.zeros((H, W), np.uint8))
    (tmp_path / 'dir' / 'left.png').mkdir(parents=True)  # a folder, not an image
    scenes = ['a', 'run1/000003', 'run2/cam_front/000010']
    assert list_scenes(NAME, tmp_path) == scenes
    assert [s.scene for s in load_dataset(NAME, tmp_path)] == scenes
    # <root>/stereo_folder/ is taken as the data set's folder, as for every data set.
    holder = tmp_path / 'all'
    write_scene(holder / NAME / 'x')
    assert list_scenes(NAME, holder) == ['x']
    # The root itself may be the one scene: its id is '.'.
    single = tmp_path / 'single'
    truth = write_scene(single, disparity=3)
    assert list_scenes(NAME, single) == ['.']
    sample = load_scene(NAME, single, '.')
    assert (sample.dataset, sample.scene) == (NAME, '.')
    same(sample.disparity, truth)


@pytest.mark.parametrize('form', ['npy', 'pfm', 'png'])
def test_each_disparity_form_loads_with_its_unknown_marker(tmp_path: Path, form: str) -> None:
    truth = write_scene(tmp_path / 's', disparity=5, form=form)
    sample = load_scene(NAME, tmp_path, 's')
    left, right, _ = pair(5)
    np.testing.assert_array_equal(sample.left, left)
    np.testing.assert_array_equal(sample.right, right)
    assert sample.disparity.dtype == np.float32 and sample.shape == (H, W)
    same(sample.disparity, truth)
    assert np.isnan(sample.disparity[:, :5]).all()
    assert sample.nonocc is None and sample.calib is None


def test_npy_zero_nan_inf_and_negative_are_unknown(tmp_path: Path) -> None:
    write_scene(tmp_path / 's')
    values = np.full((H, W), 2.5, np.float64)  # float64 and integers are taken too
    values[0, :4] = (0.0, np.nan, np.inf, -1.0)
    np.save(tmp_path / 's' / 'disparity.npy', values)
    disparity = load_scene(NAME, tmp_path, 's').disparity
    assert np.isnan(disparity[0, :4]).all()
    assert (disparity[0, 4:] == 2.5).all() and (disparity[1:] == 2.5).all()
    np.save(tmp_path / 's' / 'disparity.npy', np.full((H, W), 7, np.uint16))
    assert (load_scene(NAME, tmp_path, 's').disparity == 7).all()


def test_pfm_keeps_zero_and_marks_inf_and_nan_unknown(tmp_path: Path) -> None:
    # A simulator's sky at infinity is disparity 0, a known value in a PFM.
    write_scene(tmp_path / 's', form='pfm')
    values = np.full((H, W), 1.25, np.float32)
    values[0, :3] = (0.0, np.inf, np.nan)
    write_pfm(tmp_path / 's' / 'disparity.pfm', values)
    disparity = load_scene(NAME, tmp_path, 's').disparity
    assert disparity[0, 0] == 0.0 and np.isnan(disparity[0, 1:3]).all()
    assert (disparity[1:] == 1.25).all()


def test_png_is_16_bit_kitti_and_8_bit_is_refused(tmp_path: Path) -> None:
    write_scene(tmp_path / 's', form='png')
    stored = np.zeros((H, W), np.uint16)
    stored[1, 1] = 1000  # 1000 / 256 = 3.90625
    cv2.imwrite(str(tmp_path / 's' / 'disparity.png'), stored)
    disparity = load_scene(NAME, tmp_path, 's').disparity
    assert disparity[1, 1] == 3.90625 and np.isfinite(disparity).sum() == 1
    cv2.imwrite(str(tmp_path / 's' / 'disparity.png'), np.full((H, W), 4, np.uint8))
    with pytest.raises(DataError, match=r'16-bit.*got 8-bit.*disparity\.npy or disparity\.pfm'):
        load_scene(NAME, tmp_path, 's')


@pytest.mark.parametrize(('suffix', 'grey'), [('.jpg', False), ('.ppm', False), ('.png', True)])
def test_other_image_files_and_grey(tmp_path: Path, suffix: str, grey: bool) -> None:
    write_scene(tmp_path / 's', suffix=suffix, grey=grey)
    sample = load_scene(NAME, tmp_path, 's')
    assert sample.left.shape == ((H, W) if grey else (H, W, 3))
    assert sample.left.dtype == np.uint8


def test_nonocc_mask_and_calibration(tmp_path: Path) -> None:
    folder = tmp_path / 's'
    write_scene(folder)
    mask = np.full((H, W), 255, np.uint8)
    mask[:, :10] = 0
    cv2.imwrite(str(folder / 'nonocc.png'), mask)
    (folder / 'calib.txt').write_text(CALIB)
    sample = load_scene(NAME, tmp_path, 's')
    assert sample.nonocc is not None and sample.nonocc.dtype == np.bool_
    np.testing.assert_array_equal(sample.nonocc, mask == 255)
    calib = sample.calib
    assert calib is not None
    assert (calib.fx, calib.cx, calib.cy, calib.doffs) == (100.0, 30.0, 20.0, 1.5)
    assert calib.baseline == pytest.approx(0.12)
    # A 0/1 mask would make every pixel occluded: refused with the values it holds.
    cv2.imwrite(str(folder / 'nonocc.png'), (mask == 255).astype(np.uint8))
    with pytest.raises(DataError, match=r'marks no pixel visible.*255.*got values \[0, 1\]'):
        load_scene(NAME, tmp_path, 's')


def test_a_root_without_scenes_says_the_layout_and_what_folders_lack(tmp_path: Path) -> None:
    with pytest.raises(DataError, match=r'no stereo_folder stereo pairs .*left\.png \+ right'):
        list_scenes(NAME, tmp_path)
    folder = tmp_path / 'drive' / '0001'
    folder.mkdir(parents=True)
    cv2.imwrite(str(folder / 'left.png'), np.zeros((H, W), np.uint8))
    cv2.imwrite(str(folder / 'right.png'), np.zeros((H, W), np.uint8))
    np.save(folder / 'disp.npy', np.zeros((H, W), np.float32))  # not a name it reads
    with pytest.raises(DataError) as info:
        list_scenes(NAME, tmp_path)
    message = str(info.value)
    assert 'expected <root>/<scene' in message
    assert 'drive/0001 has no disparity (disparity.pfm, disparity.npy, disparity.png)' in message
    assert 'right image' not in message.split('folders with a left image')[1]
    with pytest.raises(DataError, match="stereo_folder scene 'drive/0001' not found"):
        load_scene(NAME, tmp_path, 'drive/0001')
    with pytest.raises(DataError, match='not found'):
        load_scene(NAME, tmp_path / 'drive', '../drive/0001')


def test_two_disparity_files_are_refused(tmp_path: Path) -> None:
    folder = tmp_path / 's'
    write_scene(folder, form='npy')
    write_scene(folder, form='pfm')
    assert list_scenes(NAME, tmp_path) == ['s']
    with pytest.raises(
        DataError, match=r"scene 's' holds 2 disparity files \(disparity\.pfm, disparity\.npy\)"
    ):
        load_scene(NAME, tmp_path, 's')
    (folder / 'disparity.pfm').unlink()
    write_scene(folder, suffix='.jpg')  # left.png and left.jpg
    with pytest.raises(DataError, match=r'holds 2 left image files \(left\.png, left\.jpg\)'):
        load_scene(NAME, tmp_path, 's')


def test_a_disparity_of_another_size_names_both_shapes_and_the_files(tmp_path: Path) -> None:
    folder = tmp_path / 's'
    write_scene(folder)
    np.save(folder / 'disparity.npy', np.ones((H // 2, W // 2), np.float32))
    with pytest.raises(DataError) as info:
        load_scene(NAME, tmp_path, 's')
    message = str(info.value)
    assert f'shape {(H, W)}' in message and f'{(H // 2, W // 2)}' in message
    assert str(folder / 'disparity.npy') in message and str(folder / 'left.png') in message


def test_a_map_of_negative_disparities_is_refused(tmp_path: Path) -> None:
    # The right-to-left sign convention would be read as 'all unknown' and score nothing.
    folder = tmp_path / 's'
    write_scene(folder)
    np.save(folder / 'disparity.npy', np.full((H, W), -4.0, np.float32))
    with pytest.raises(DataError, match=r'every known disparity is negative \(min -4\)'):
        load_scene(NAME, tmp_path, 's')
    three = np.full((H, W, 3), 2.0, np.float32)
    np.save(folder / 'disparity.npy', three)
    with pytest.raises(DataError, match=r'expected an \(H, W\) real-valued array'):
        load_scene(NAME, tmp_path, 's')


def test_cva_evaluate_end_to_end(tmp_path: Path) -> None:
    from cva_confidence_ros.evaluation.cli import main

    root = tmp_path / 'data'
    write_scene(root / 'seq' / '000', disparity=4, form='npy', seed=0)
    write_scene(root / 'seq' / '001', disparity=6, form='pfm', seed=1)
    write_scene(root / 'other', disparity=5, form='png', seed=2)
    out = tmp_path / 'eval.json'
    code = main(['--data-root', str(root), '--dataset', NAME, '--matchers', 'census_bm',
                 '--methods', 'pkrn', '--max-disparity', '16', '--json', str(out)])
    assert code == 0
    records = json.loads(out.read_text())
    assert [(r['dataset'], r['scene']) for r in records] == [
        (NAME, 'other'), (NAME, 'seq/000'), (NAME, 'seq/001')
    ]
    for record in records:
        # The ground truth is right: Census-BM is wrong on few of the textured pixels.
        assert record['n_pixels'] > 0.9 * H * (W - 6)
        assert record['error_rate'] < 0.05 and 0 <= record['auc_opt'] <= record['auc']


@pytest.mark.usefixtures('_restore_threads')
def test_cva_train_end_to_end(tmp_path: Path) -> None:
    from cva_confidence_ros.training.cli import main

    root = tmp_path / 'data'
    write_scene(root / 'a', disparity=4, seed=0)
    write_scene(root / 'b', disparity=7, form='png', seed=1)
    out = tmp_path / 'run'
    weights = out / 'cvanet_census_bm_d16.pt'
    code = main(['--datasets', NAME, '--data-root', str(root), '--max-disparity', '16',
                 '--samples-per-epoch', '32', '--epochs', '1', '--epochs-low-lr', '0',
                 '--synthetic', '0', '--val-synthetic', '1', '--threads', '1',
                 '--out', str(out), '--weights-out', str(weights), '--no-progress'])
    assert code == 0
    assert weights.is_file()
    assert 'stereo_folder/a' in (out / 'train.log').read_text()


def test_cva_bag_from_dataset_with_calibration(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip('rosbags')
    from msg_tools.bag_from_dataset import main

    root = tmp_path / 'data'
    write_scene(root / 'a')
    (root / 'a' / 'calib.txt').write_text(CALIB)
    bag = tmp_path / 'bag'
    assert main(['--data-root', str(root), '--dataset', NAME, '--out', str(bag)]) == 0
    captured = capsys.readouterr()
    assert f'wrote 1 frames to {bag}' in captured.out
    assert 'has no calibration' not in captured.err
    assert (bag / 'metadata.yaml').is_file()
