"""Data sets as users download them: partial downloads, archives extracted a level off, other
names and cases, symlinked folders. A scene left out must be named with what it lacks."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from cva_confidence_ros.datasets import (
    list_scenes,
    load_scene,
    skipped_notice,
    skipped_scenes,
    write_pfm,
)
from cva_confidence_ros.errors import DataError

H, W = 6, 12


def _image(path: Path, seed: int = 0) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    assert cv2.imwrite(str(path), rng.integers(0, 256, (H, W, 3), np.uint8))


def _kitti_gt(path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), np.full((H, W), 3 * 256, np.uint16))


def _pfm(path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_pfm(path, np.full((H, W), 2.5, np.float32))


def _kitti2015(base: Path, scenes: tuple[str, ...] = ('000000',)) -> None:
    for scene in scenes:
        _image(base / 'image_2' / f'{scene}_10.png')
        _image(base / 'image_3' / f'{scene}_10.png', 1)
        _kitti_gt(base / 'disp_occ_0' / f'{scene}_10.png')


def _middlebury(folder: Path, names: tuple[str, ...] = ('im0.png', 'im1.png')) -> None:
    for seed, name in enumerate(names):
        _image(folder / name, seed)


def test_a_kitti_scene_without_its_right_image_is_named_testing_is_not(tmp_path: Path) -> None:
    # 000005 has ground truth and a left image but no right one: it was left out unsaid.
    _kitti2015(tmp_path / 'training')
    _image(tmp_path / 'training' / 'image_2' / '000005_10.png')
    _kitti_gt(tmp_path / 'training' / 'disp_occ_0' / '000005_10.png')
    _image(tmp_path / 'testing' / 'image_2' / '000007_10.png')  # no ground truth: no scene
    _image(tmp_path / 'training' / 'image_2' / '000000_11.png')  # the second frame
    assert list_scenes('kitti2015', tmp_path) == ['000000']
    assert skipped_scenes('kitti2015', tmp_path) == [('000005', 'no image_3/000005_10.png')]
    assert skipped_notice('kitti2015', tmp_path) == (
        'kitti2015: 1 scene(s) left out, a file missing: 000005 has no image_3/000005_10.png'
    )
    with pytest.raises(DataError, match="'000005' not found .*: it has no image_3/000005_10"):
        load_scene('kitti2015', tmp_path, '000005')
    complete = tmp_path / 'complete'
    _kitti2015(complete / 'training')
    _image(complete / 'testing' / 'image_2' / '000007_10.png')
    assert skipped_scenes('kitti2015', complete) == []
    assert skipped_notice('kitti2015', complete) == ''


def test_kitti2012_without_any_image_of_a_scene_names_both_layouts(tmp_path: Path) -> None:
    base = tmp_path / 'training'
    _image(base / 'colored_0' / '000001_10.png')
    _image(base / 'colored_1' / '000001_10.png', 1)
    _kitti_gt(base / 'disp_occ' / '000001_10.png')
    _kitti_gt(base / 'disp_occ' / '000002_10.png')
    _image(base / 'image_0' / '000003_10.png')
    _kitti_gt(base / 'disp_occ' / '000003_10.png')
    assert skipped_scenes('kitti2012', tmp_path) == [
        ('000002', 'no images ({colored_0,colored_1 or image_0,image_1}/000002_10.png)'),
        ('000003', 'no image_1/000003_10.png'),
    ]


def test_a_middlebury_folder_without_im1_names_the_other_exposures(tmp_path: Path) -> None:
    split = tmp_path / 'MiddEval3' / 'trainingQ'
    _middlebury(split / 'Adirondack')
    _pfm(split / 'Adirondack' / 'disp0GT.pfm')
    _middlebury(split / 'Piano', ('im0.png', 'im1E.png', 'im1L.png'))
    _pfm(split / 'Piano' / 'disp0GT.pfm')
    (split / 'notes').mkdir()  # a folder of something else is no scene
    assert list_scenes('middlebury2014', tmp_path) == ['Adirondack']
    assert skipped_scenes('middlebury2014', tmp_path) == [
        ('Piano', 'no im1.png (found im1E.png, im1L.png)')
    ]
    with pytest.raises(DataError, match=r"'Piano' not found .*: it has no im1\.png"):
        load_scene('middlebury2014', tmp_path, 'Piano')


def test_images_without_the_ground_truth_download_say_so(tmp_path: Path) -> None:
    # MiddEval3 and ETH3D ship the ground truth as a download of its own: without it, the
    # error said only 'no pairs found'.
    _middlebury(tmp_path / 'mb' / 'trainingQ' / 'Adirondack')
    with pytest.raises(DataError, match=r'Adirondack has no disp0GT\.pfm \(or disp0\.pfm\)'):
        list_scenes('middlebury2014', tmp_path / 'mb')
    _middlebury(tmp_path / 'eth' / 'two_view_training' / 'delivery_area_1l')
    with pytest.raises(
        DataError,
        match=r'delivery_area_1l has no disp0GT\.pfm \(here or in two_view_training_gt/',
    ):
        list_scenes('eth3d', tmp_path / 'eth')
    _pfm(tmp_path / 'eth' / 'two_view_training_gt' / 'delivery_area_1l' / 'disp0GT.pfm')
    assert list_scenes('eth3d', tmp_path / 'eth') == ['delivery_area_1l']


def test_other_cases_and_suffixes_are_named_as_found(tmp_path: Path) -> None:
    scene = tmp_path / 'mb' / 'trainingQ' / 'Art'
    _middlebury(scene, ('IM0.PNG', 'IM1.PNG'))
    _pfm(scene / 'DISP0GT.PFM')
    with pytest.raises(DataError) as info:
        list_scenes('middlebury2014', tmp_path / 'mb')
    assert 'Art has no im0.png (found IM0.PNG) and no im1.png (found IM1.PNG)' in str(info.value)
    assert '(found DISP0GT.PFM)' in str(info.value)
    base = tmp_path / 'kitti' / 'training'
    _image(base / 'image_2' / '000000_10.jpg')
    _image(base / 'image_3' / '000000_10.jpg')
    _kitti_gt(base / 'disp_occ_0' / '000000_10.png')
    with pytest.raises(DataError, match=r'no image_2/000000_10\.png \(found 000000_10\.jpg\)'):
        list_scenes('kitti2015', tmp_path / 'kitti')


def test_a_stereo_folder_scene_without_a_right_image_is_named(tmp_path: Path) -> None:
    for scene in ('a', 'b'):
        _image(tmp_path / scene / 'left.png')
        _pfm(tmp_path / scene / 'disparity.pfm')
    _image(tmp_path / 'a' / 'right.png', 1)
    assert list_scenes('stereo_folder', tmp_path) == ['a']
    assert skipped_scenes('stereo_folder', tmp_path) == [
        ('b', 'no right image (right.png, right.jpg, right.jpeg, right.ppm, right.pgm)')
    ]


def test_symlinked_scene_folders_are_found(tmp_path: Path) -> None:
    # rglob does not go into symlinked folders: scenes linked in from another disk were
    # not found ('no stereo_folder stereo pairs').
    disk = tmp_path / 'disk' / 'scene'
    _image(disk / 'left.png')
    _image(disk / 'right.png', 1)
    _pfm(disk / 'disparity.pfm')
    root = tmp_path / 'root'
    root.mkdir()
    os.symlink(disk, root / 'linked')
    os.symlink(root, root / 'loop')  # a link back up is followed once, not forever
    assert list_scenes('stereo_folder', root) == ['linked']
    assert load_scene('stereo_folder', root, 'linked').shape == (H, W)
    frames = tmp_path / 'tartan' / 'P000'
    _image(frames / '000000_left.png')
    _image(frames / '000000_right.png', 1)
    frames.mkdir(parents=True, exist_ok=True)
    np.save(frames / '000000_left_disp.npy', np.full((H, W), 2.0, np.float32))
    (tmp_path / 'tartan_root').mkdir()
    os.symlink(frames, tmp_path / 'tartan_root' / 'P000')
    assert list_scenes('tartanair', tmp_path / 'tartan_root') == ['P000/000000']


def test_a_root_one_level_off_points_at_the_right_one(tmp_path: Path) -> None:
    # The KITTI zip extracted into a folder of its name, and a root given one level too deep.
    _kitti2015(tmp_path / 'data_scene_flow' / 'training')
    with pytest.raises(
        DataError, match=f'pairs found under {tmp_path / "data_scene_flow"}: use that as root'
    ):
        list_scenes('kitti2015', tmp_path)
    with pytest.raises(
        DataError,
        match=f'pairs found under {tmp_path / "data_scene_flow" / "training"}: use that',
    ):
        list_scenes('kitti2015', tmp_path / 'data_scene_flow' / 'training' / 'image_2')
    # KITTI 2015 given as KITTI 2012.
    with pytest.raises(DataError, match=r"pairs of data set\(s\) \['kitti2015'\] found there"):
        list_scenes('kitti2012', tmp_path / 'data_scene_flow')


def test_the_full_size_middlebury_2014_download_loads(tmp_path: Path) -> None:
    # <Scene>-perfect/ with disp0.pfm (no disp0GT.pfm) and the exposures im1E/im1L.
    for scene in ('Adirondack-perfect', 'Jadeplant-imperfect'):
        _middlebury(tmp_path / scene, ('im0.png', 'im1.png', 'im1E.png', 'im1L.png'))
        _pfm(tmp_path / scene / 'disp0.pfm')
        _pfm(tmp_path / scene / 'disp1.pfm')
    assert list_scenes('middlebury2014', tmp_path) == ['Adirondack-perfect', 'Jadeplant-imperfect']
    sample = load_scene('middlebury2014', tmp_path, 'Adirondack-perfect')
    assert np.all(sample.disparity == np.float32(2.5))


def test_an_unknown_scene_lists_scenes_that_exist(tmp_path: Path) -> None:
    _kitti2015(tmp_path / 'training', tuple(f'{n:06d}' for n in range(7)))
    with pytest.raises(DataError) as info:
        load_scene('kitti2015', tmp_path, '000009')
    assert str(info.value).endswith(
        f'not found under {tmp_path}; 7 scene(s) there: 000000, 000001, 000002, 000003, '
        '000004, …'
    )


def _partial_middlebury(root: Path) -> None:
    from cva_confidence_ros.datasets.synthetic import synthetic_pair

    for scene in ('A', 'B'):
        folder = root / 'middlebury2014' / 'trainingQ' / scene
        folder.mkdir(parents=True)
        pair = synthetic_pair(7, 32, 48, 16)
        cv2.imwrite(str(folder / 'im0.png'), cv2.cvtColor(pair.left, cv2.COLOR_RGB2BGR))
        if scene == 'A':
            cv2.imwrite(str(folder / 'im1.png'), cv2.cvtColor(pair.right, cv2.COLOR_RGB2BGR))
        disparity = np.where(np.isfinite(pair.disparity), pair.disparity, np.inf)
        write_pfm(folder / 'disp0GT.pfm', disparity.astype(np.float32))


def test_cva_evaluate_and_cva_table1_name_a_left_out_scene_once(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from cva_confidence_ros.evaluation.cli import main as evaluate
    from cva_confidence_ros.evaluation.table1 import main as table1

    root = tmp_path / 'data'
    _partial_middlebury(root)
    notice = 'middlebury2014: 1 scene(s) left out, a file missing: B has no im1.png'
    assert evaluate(['--data-root', str(root), '--dataset', 'middlebury2014', '--matchers',
                     'census_bm', '--methods', 'pkrn', '--max-disparity', '16',
                     '--max-pixels', '100', '--json', str(tmp_path / 'r.json'),
                     '--allow-missing-files']) == 0
    assert capsys.readouterr().err.count(notice) == 1
    assert table1(['--data-root', str(root), '--out', str(tmp_path / 'out'), '--matchers',
                   'census_bm', '--methods', 'pkrn', '--max-disparity', '16',
                   '--max-pixels', '100', '--protocol', 'develop', '--allow-missing-files']) == 0
    assert capsys.readouterr().err.count(notice) == 1
