"""Loaders on tiny files written in each data set's layout (no shared data needed)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
import shutil

import cv2
import numpy as np
import pytest

from cva_confidence_ros.datasets import (
    DATASETS,
    DEVELOP_DATASETS,
    TRAIN_DATASETS,
    Calibration,
    StereoSample,
    list_scenes,
    load_dataset,
    load_scene,
    write_pfm,
)
from cva_confidence_ros.errors import ConfigError, DataError

H, W, D = 6, 12, 2.5


def make_pair(seed: int, gray: bool = False) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    shape = (H, W) if gray else (H, W, 3)
    return rng.integers(0, 256, shape, dtype=np.uint8), rng.integers(0, 256, shape, np.uint8)


def expected_disparity(value: float = D) -> np.ndarray:
    disparity = np.full((H, W), value, np.float32)
    disparity[0, 0] = np.nan
    return disparity


def write_image(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    assert cv2.imwrite(str(path), image)


def write_encoded(path: Path, scale: float, dtype: type = np.uint8) -> None:
    """Disparity D stored as D * scale, 0 (unknown) at (0, 0)."""
    raw = np.full((H, W), round(D * scale), dtype)
    raw[0, 0] = 0
    write_image(path, raw)


def write_gt_pfm(path: Path, value: float = D) -> None:
    disparity = np.full((H, W), value, np.float32)
    disparity[0, 0] = np.inf
    path.parent.mkdir(parents=True, exist_ok=True)
    write_pfm(path, disparity)


MIDDLEBURY_CALIB = (
    'cam0=[100 0 5.5; 0 100 2.5; 0 0 1]\ncam1=[100 0 7.5; 0 100 2.5; 0 0 1]\n'
    'doffs=2\nbaseline=150\nwidth=12\nheight=6\nndisp=8\n'
)
KITTI_P = {
    'left': '100 0 5 20 0 100 3 0 0 0 1 0',
    'right': '100 0 5 -30 0 100 3 0 0 0 1 0',
}


def check_sample(
    sample: StereoSample,
    name: str,
    scene: str,
    pair: tuple[np.ndarray, np.ndarray],
    disparity: np.ndarray | None = None,
) -> None:
    assert sample.dataset == name and sample.scene == scene
    np.testing.assert_array_equal(sample.left, pair[0])
    np.testing.assert_array_equal(sample.right, pair[1])
    assert sample.disparity.dtype == np.float32
    expected = expected_disparity() if disparity is None else disparity
    np.testing.assert_allclose(sample.disparity, expected, rtol=1e-6, equal_nan=True)


def test_kitti2012(tmp_path: Path) -> None:
    base = tmp_path / 'training'
    colour, gray = make_pair(0), make_pair(1, gray=True)
    write_image(base / 'colored_0' / '000003_10.png', colour[0])
    write_image(base / 'colored_1' / '000003_10.png', colour[1])
    write_encoded(base / 'disp_occ' / '000003_10.png', 256.0, np.uint16)
    noc = np.full((H, W), round(D * 256), np.uint16)
    noc[:, :3] = 0
    write_image(base / 'disp_noc' / '000003_10.png', noc)
    (base / 'calib').mkdir()
    (base / 'calib' / '000003.txt').write_text(
        f'P0: {KITTI_P["left"]}\nP1: {KITTI_P["right"]}\n'
        f'P2: {KITTI_P["left"]}\nP3: {KITTI_P["right"]}\n'
    )
    write_image(base / 'image_0' / '000004_10.png', gray[0])
    write_image(base / 'image_1' / '000004_10.png', gray[1])
    write_encoded(base / 'disp_occ' / '000004_10.png', 256.0, np.uint16)
    write_encoded(base / 'disp_occ' / '000005_10.png', 256.0, np.uint16)  # no images: skipped

    assert list_scenes('kitti2012', tmp_path) == ['000003', '000004']
    sample = load_scene('kitti2012', tmp_path, '000003')
    check_sample(sample, 'kitti2012', '000003', colour)
    assert sample.nonocc is not None and sample.nonocc.sum() == H * (W - 3)
    assert sample.calib == Calibration(fx=100, fy=100, cx=5, cy=3, baseline=0.5, doffs=0)
    gray_sample = load_scene('kitti2012', tmp_path / 'training', '000004')
    check_sample(gray_sample, 'kitti2012', '000004', gray)
    assert gray_sample.nonocc is None and gray_sample.calib is None


def test_kitti2015(tmp_path: Path) -> None:
    base = tmp_path / 'training'
    pair = make_pair(2)
    write_image(base / 'image_2' / '000000_10.png', pair[0])
    write_image(base / 'image_3' / '000000_10.png', pair[1])
    write_encoded(base / 'disp_occ_0' / '000000_10.png', 256.0, np.uint16)
    (base / 'calib_cam_to_cam').mkdir()
    (base / 'calib_cam_to_cam' / '000000.txt').write_text(
        f'S_rect_02: 12 6\nP_rect_02: {KITTI_P["left"]}\nP_rect_03: {KITTI_P["right"]}\n'
    )
    assert list_scenes('kitti2015', tmp_path) == ['000000']
    sample = load_scene('kitti2015', tmp_path, '000000', split='training')
    check_sample(sample, 'kitti2015', '000000', pair)
    assert sample.calib is not None and sample.calib.baseline == pytest.approx(0.5)


def test_middlebury2014(tmp_path: Path) -> None:
    folder = tmp_path / 'trainingH' / 'Piano'
    pair = make_pair(3)
    write_image(folder / 'im0.png', pair[0])
    write_image(folder / 'im1.png', pair[1])
    write_gt_pfm(folder / 'disp0GT.pfm')
    mask = np.full((H, W), 255, np.uint8)
    mask[1, :4] = 128
    mask[0, 0] = 0
    write_image(folder / 'mask0nocc.png', mask)
    (folder / 'calib.txt').write_text(MIDDLEBURY_CALIB)
    write_image(tmp_path / 'trainingH' / 'Empty' / 'im0.png', pair[0])  # no GT: skipped

    assert list_scenes('middlebury2014', tmp_path, split='trainingH') == ['Piano']
    with pytest.raises(DataError, match='trainingQ'):
        list_scenes('middlebury2014', tmp_path)  # default split trainingQ is absent
    sample = load_scene('middlebury2014', tmp_path, 'Piano', split='trainingH')
    check_sample(sample, 'middlebury2014', 'Piano', pair)
    assert sample.nonocc is not None
    assert sample.nonocc.sum() == H * W - 5 and not sample.nonocc[1, :4].any()
    assert sample.calib == Calibration(fx=100, fy=100, cx=5.5, cy=2.5, baseline=0.15, doffs=2)


def test_middlebury2001_three_layouts(tmp_path: Path) -> None:
    tsukuba, venus, map_pair = make_pair(4), make_pair(5), make_pair(6, gray=True)
    write_image(tmp_path / 'tsukuba' / 'scene1.row3.col3.ppm', tsukuba[0])
    write_image(tmp_path / 'tsukuba' / 'scene1.row3.col4.ppm', tsukuba[1])
    write_encoded(tmp_path / 'tsukuba' / 'truedisp.row3.col3.pgm', 16.0)
    for index, image in zip((2, 6), venus, strict=True):
        write_image(tmp_path / 'venus' / f'im{index}.ppm', image)
    write_encoded(tmp_path / 'venus' / 'disp2.pgm', 8.0)
    write_image(tmp_path / 'map' / 'im0.pgm', map_pair[0])
    write_image(tmp_path / 'map' / 'im1.pgm', map_pair[1])
    write_encoded(tmp_path / 'map' / 'disp0.pgm', 8.0)

    assert list_scenes('middlebury2001', tmp_path) == ['map', 'tsukuba', 'venus']
    for scene, pair in (('tsukuba', tsukuba), ('venus', venus), ('map', map_pair)):
        check_sample(load_scene('middlebury2001', tmp_path, scene), 'middlebury2001', scene, pair)


def test_middlebury2003_both_namings_and_size_scale(tmp_path: Path) -> None:
    cones, teddy = make_pair(7), make_pair(8)
    write_image(tmp_path / 'cones' / 'cones_image_02.png', cones[0])
    write_image(tmp_path / 'cones' / 'cones_image_06.png', cones[1])
    write_encoded(tmp_path / 'cones' / 'cones_disp_02.png', 4.0)  # narrow image: quarter size
    write_image(tmp_path / 'teddy' / 'im2.png', teddy[0])
    write_image(tmp_path / 'teddy' / 'im6.png', teddy[1])
    write_encoded(tmp_path / 'teddy' / 'disp2.png', 4.0)
    assert list_scenes('middlebury2003', tmp_path) == ['cones', 'teddy']
    check_sample(load_scene('middlebury2003', tmp_path, 'cones'), 'middlebury2003', 'cones', cones)
    check_sample(load_scene('middlebury2003', tmp_path, 'teddy'), 'middlebury2003', 'teddy', teddy)
    # An explicit size overrides the width rule: full size stores d × 1.
    full = load_scene('middlebury2003', tmp_path, 'teddy', split='full')
    np.testing.assert_allclose(full.disparity, expected_disparity(4 * D), equal_nan=True)


def test_middlebury2005_and_2006(tmp_path: Path) -> None:
    art, laundry, aloe = make_pair(9), make_pair(10), make_pair(11)
    for name, image in (('view1.png', art[0]), ('view5.png', art[1])):
        write_image(tmp_path / 'ThirdSize' / 'Art' / name, image)
    write_encoded(tmp_path / 'ThirdSize' / 'Art' / 'disp1.png', 3.0)
    write_image(tmp_path / 'Laundry' / 'img0.png', laundry[0])
    write_image(tmp_path / 'Laundry' / 'img1.png', laundry[1])
    write_encoded(tmp_path / 'Laundry' / 'disp1.png', 3.0)
    assert list_scenes('middlebury2005', tmp_path, split='ThirdSize') == ['Art']
    assert list_scenes('middlebury2005', tmp_path) == ['Laundry']
    third = expected_disparity(round(D * 3) / 3)  # stored as 8: d = 8 / 3
    check_sample(
        load_scene('middlebury2005', tmp_path, 'Art', split='ThirdSize'),
        'middlebury2005',
        'Art',
        art,
        third,
    )
    # Width 12 < 550: third size, d = v / 3.
    check_sample(
        load_scene('middlebury2005', tmp_path, 'Laundry'),
        'middlebury2005',
        'Laundry',
        laundry,
        third,
    )

    root2006 = tmp_path / 'm2006'
    write_image(root2006 / 'aloe' / 'aloeL.png', aloe[0])
    write_image(root2006 / 'aloe' / 'aloeR.png', aloe[1])
    write_encoded(root2006 / 'aloe' / 'aloeGT.png', 1.0)
    write_encoded(root2006 / 'aloe' / 'ignored_disp.png', 1.0)
    assert list_scenes('middlebury2006', root2006) == ['aloe']
    sample = load_scene('middlebury2006', root2006, 'aloe', split='FullSize')
    check_sample(sample, 'middlebury2006', 'aloe', aloe, expected_disparity(float(round(D))))


def test_eth3d_gt_beside_or_in_gt_folder(tmp_path: Path) -> None:
    first, second = make_pair(12), make_pair(13)
    base = tmp_path / 'two_view_training'
    for scene, pair in (('delivery_area_1l', first), ('playground_1l', second)):
        write_image(base / scene / 'im0.png', pair[0])
        write_image(base / scene / 'im1.png', pair[1])
    (base / 'delivery_area_1l' / 'calib.txt').write_text(MIDDLEBURY_CALIB)
    write_gt_pfm(tmp_path / 'two_view_training_gt' / 'delivery_area_1l' / 'disp0GT.pfm')
    mask = np.full((H, W), 255, np.uint8)
    mask[2, 2] = 128
    write_image(tmp_path / 'two_view_training_gt' / 'delivery_area_1l' / 'mask0nocc.png', mask)
    write_gt_pfm(base / 'playground_1l' / 'disp0.pfm')
    write_image(base / 'no_gt' / 'im0.png', first[0])
    write_image(base / 'no_gt' / 'im1.png', first[1])

    assert list_scenes('eth3d', tmp_path) == ['delivery_area_1l', 'playground_1l']
    sample = load_scene('eth3d', tmp_path, 'delivery_area_1l')
    check_sample(sample, 'eth3d', 'delivery_area_1l', first)
    assert sample.nonocc is not None and sample.nonocc.sum() == H * W - 1
    assert sample.calib is not None and sample.calib.fx == 100
    second_sample = load_scene('eth3d', tmp_path, 'playground_1l')
    check_sample(second_sample, 'eth3d', 'playground_1l', second)
    assert second_sample.nonocc is None


def test_flyingthings3d(tmp_path: Path) -> None:
    train, test = make_pair(14), make_pair(15)
    for pass_name, split, seq, pair in (
        ('frames_cleanpass', 'TRAIN', 'A/0001', train),
        ('frames_finalpass', 'TEST', 'B/0002', test),
    ):
        write_image(tmp_path / pass_name / split / seq / 'left' / '0006.png', pair[0])
        write_image(tmp_path / pass_name / split / seq / 'right' / '0006.png', pair[1])
        gt = np.full((H, W), D, np.float32)
        gt[0, 0] = -1.0  # negative disparities are invalid: NaN
        (tmp_path / 'disparity' / split / seq / 'left').mkdir(parents=True)
        write_pfm(tmp_path / 'disparity' / split / seq / 'left' / '0006.pfm', gt)

    assert list_scenes('flyingthings3d', tmp_path) == ['TEST/B/0002/0006', 'TRAIN/A/0001/0006']
    assert list_scenes('flyingthings3d', tmp_path, split='TRAIN') == ['TRAIN/A/0001/0006']
    sample = load_scene('flyingthings3d', tmp_path, 'TEST/B/0002/0006')
    check_sample(sample, 'flyingthings3d', 'TEST/B/0002/0006', test)
    with pytest.raises(DataError, match='not found'):
        load_scene('flyingthings3d', tmp_path, 'TRAIN/A/0001')


def test_sceneflow_extra_two_layouts(tmp_path: Path) -> None:
    loose, sttr = make_pair(16), make_pair(17)
    folder = tmp_path / 'SceneFlow_FlyingThings3D'
    write_image(folder / 'Left' / '0007.png', loose[0])
    write_image(folder / 'Right' / '0007.png', loose[1])
    write_gt_pfm(folder / 'Disparity' / '0007.pfm')
    folder = tmp_path / 'sttr_A-0001-0002'
    write_image(folder / 'RGB_cleanpass' / 'left' / 'A-0001-0002.png', sttr[0])
    write_image(folder / 'RGB_cleanpass' / 'right' / 'A-0001-0002.png', sttr[1])
    write_gt_pfm(folder / 'disparity' / 'left' / 'A-0001-0002.pfm')
    occlusion = np.zeros((H, W), np.uint8)
    occlusion[:, :3] = 255
    write_image(folder / 'occlusion' / 'left' / 'A-0001-0002.png', occlusion)

    scenes = list_scenes('sceneflow_extra', tmp_path)
    assert scenes == ['SceneFlow_FlyingThings3D/0007', 'sttr_A-0001-0002/A-0001-0002']
    first = load_scene('sceneflow_extra', tmp_path, scenes[0])
    check_sample(first, 'sceneflow_extra', scenes[0], loose)
    assert first.nonocc is None
    second = load_scene('sceneflow_extra', tmp_path, scenes[1])
    check_sample(second, 'sceneflow_extra', scenes[1], sttr)
    assert second.nonocc is not None
    np.testing.assert_array_equal(second.nonocc, occlusion == 0)


def test_tartanair_flat_and_original_layout(tmp_path: Path) -> None:
    flat, nested = make_pair(18), make_pair(19)
    folder = tmp_path / 'OldTown' / 'EasyP000'
    write_image(folder / '001116_left.png', flat[0])
    write_image(folder / '001116_right.png', flat[1])
    np.save(folder / '001116_left_disp.npy', np.full((H, W), D, np.float32))
    folder = tmp_path / 'abandonedfactory' / 'Easy' / 'P001'
    write_image(folder / 'image_left' / '000010_left.png', nested[0])
    write_image(folder / 'image_right' / '000010_right.png', nested[1])
    (folder / 'depth_left').mkdir()
    np.save(folder / 'depth_left' / '000010_left_depth.npy', np.full((H, W), 32.0, np.float32))

    scenes = list_scenes('tartanair', tmp_path)
    assert scenes == ['OldTown/EasyP000/001116', 'abandonedfactory/Easy/P001/000010']
    sample = load_scene('tartanair', tmp_path, scenes[0])
    check_sample(sample, 'tartanair', scenes[0], flat, np.full((H, W), D, np.float32))
    assert sample.calib is not None and sample.calib.fx * sample.calib.baseline == 80.0
    # Depth 32 m → d = 320 px × 0.25 m / 32 m = 2.5 px.
    from_depth = load_scene('tartanair', tmp_path, scenes[1])
    check_sample(from_depth, 'tartanair', scenes[1], nested, np.full((H, W), D, np.float32))


def test_tartanair_empty_or_complex_ground_truth(tmp_path: Path) -> None:
    folder = tmp_path / 'OldTown' / 'EasyP000'
    pair = make_pair(20)
    write_image(folder / '000001_left.png', pair[0])
    write_image(folder / '000001_right.png', pair[1])
    gt = folder / '000001_left_disp.npy'
    gt.write_bytes(b'')
    with pytest.raises(DataError, match='cannot read .* as a float array'):
        load_scene('tartanair', tmp_path, 'OldTown/EasyP000/000001')
    np.save(gt, np.full((H, W), D, np.complex64))
    with pytest.raises(DataError, match='real-valued array; got complex64'):
        load_scene('tartanair', tmp_path, 'OldTown/EasyP000/000001')


def test_kitti_ground_truth_must_be_16_bit(tmp_path: Path) -> None:
    base = tmp_path / 'training'
    pair = make_pair(21)
    write_image(base / 'image_2' / '000000_10.png', pair[0])
    write_image(base / 'image_3' / '000000_10.png', pair[1])
    write_encoded(base / 'disp_occ_0' / '000000_10.png', 1.0, np.uint8)  # saved as 8 bit
    with pytest.raises(DataError, match='expected a 16-bit disparity image'):
        load_scene('kitti2015', tmp_path, '000000')


def test_split_of_another_size_than_the_files_is_refused(tmp_path: Path) -> None:
    folder = tmp_path / 'cones'
    rng = np.random.default_rng(22)
    for name in ('im2.png', 'im6.png'):
        write_image(folder / name, rng.integers(0, 256, (375, 450, 3), dtype=np.uint8))
    write_image(folder / 'disp2.png', np.full((375, 450), 40, np.uint8))
    assert np.nanmax(load_scene('middlebury2003', tmp_path, 'cones').disparity) == 10.0
    with pytest.raises(DataError, match="split 'full' .* 450 px wide, the width of split "
                       "'quarter'"):
        load_scene('middlebury2003', tmp_path, 'cones', split='full')


def test_motorcycle_needs_no_root() -> None:
    assert list_scenes('motorcycle', None) == ['motorcycle']
    sample = load_scene('motorcycle', None, 'motorcycle')
    assert sample.left.shape == (500, 741, 3) and sample.left.dtype == np.uint8
    assert sample.disparity.dtype == np.float32
    assert 0.9 < np.isfinite(sample.disparity).mean() < 0.95
    assert 59.0 < sample.max_disparity < 61.0
    assert sample.calib is not None and sample.calib.doffs == pytest.approx(31.086)


def test_registry_and_splits() -> None:
    expected = {
        'kitti2012', 'kitti2015', 'middlebury2014', 'middlebury2003', 'middlebury2001',
        'middlebury2005', 'middlebury2006', 'eth3d', 'flyingthings3d', 'sceneflow_extra',
        'tartanair', 'motorcycle', 'stereo_folder',
    }
    assert set(DATASETS.names()) == expected
    assert set(DEVELOP_DATASETS) == {'kitti2015', 'middlebury2003', 'middlebury2014'}
    assert not set(TRAIN_DATASETS) & set(DEVELOP_DATASETS)
    assert 'motorcycle' not in TRAIN_DATASETS  # it is the Middlebury 2014 Motorcycle scene
    # stereo_folder is the user's own data: in neither.
    neither = {'motorcycle', 'stereo_folder'}
    assert set(TRAIN_DATASETS) | set(DEVELOP_DATASETS) == expected - neither
    assert DATASETS.get('middlebury2014').default_split == 'trainingQ'


def test_root_errors(tmp_path: Path) -> None:
    with pytest.raises(DataError) as info:
        list_scenes('kitti2015', tmp_path)
    assert str(tmp_path) in str(info.value) and 'disp_occ_0' in str(info.value)
    with pytest.raises(DataError, match='not a folder'):
        list_scenes('eth3d', tmp_path / 'missing')
    with pytest.raises(ConfigError, match='root'):
        list_scenes('kitti2012', None)
    with pytest.raises(ConfigError, match='unknown data set'):
        list_scenes('kitti2099', tmp_path)
    with pytest.raises(ConfigError, match='splits'):
        list_scenes('kitti2015', tmp_path, split='trainingQ')
    with pytest.raises(DataError, match='not found'):
        load_scene('middlebury2014', tmp_path, 'Nope')


def build_middlebury2003(root: Path, scenes: tuple[str, ...]) -> None:
    for index, scene in enumerate(scenes):
        pair = make_pair(20 + index)
        write_image(root / scene / 'im2.png', pair[0])
        write_image(root / scene / 'im6.png', pair[1])
        write_encoded(root / scene / 'disp2.png', 4.0)


def test_root_may_hold_data_sets_by_name(tmp_path: Path) -> None:
    build_middlebury2003(tmp_path / 'middlebury2003', ('cones',))
    assert list_scenes('middlebury2003', tmp_path) == ['cones']
    assert load_scene('middlebury2003', str(tmp_path), 'cones').scene == 'cones'


def test_load_dataset_is_lazy(tmp_path: Path) -> None:
    build_middlebury2003(tmp_path, ('a', 'b', 'c'))
    samples = load_dataset('middlebury2003', tmp_path)
    first = next(samples)
    assert first.scene == 'a'
    shutil.rmtree(tmp_path / 'b')  # listed already, loaded only when reached
    with pytest.raises(DataError, match="'b'"):
        next(samples)
    assert [s.scene for s in load_dataset('middlebury2003', tmp_path, max_scenes=1)] == ['a']
    with pytest.raises(DataError, match='no middlebury2003'):
        load_dataset('middlebury2003', tmp_path / 'a')
    with pytest.raises(ConfigError, match='max_scenes'):
        load_dataset('middlebury2003', tmp_path, max_scenes=-1)


@pytest.mark.parametrize(
    ('change', 'message'),
    [
        (lambda s: {'left': s['left'].astype(np.float32)}, 'uint8'),
        (lambda s: {'right': s['right'][:, :-1]}, 'same shape'),
        (lambda s: {'disparity': s['disparity'].astype(np.float64)}, 'float32'),
        (lambda s: {'nonocc': np.ones((H, W), np.uint8)}, 'bool'),
    ],
)
def test_sample_validation(change: Callable[[dict], dict], message: str) -> None:
    left, right = make_pair(30)
    fields = {'left': left, 'right': right, 'disparity': expected_disparity()}
    fields.update(change(fields))
    with pytest.raises(DataError, match=message):
        StereoSample(dataset='x', scene='y', **fields)
