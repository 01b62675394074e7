"""Review 28: ``cva-demo``, ignore masks and ``cva-mask`` (each a regression test of a fault
found there): outputs in the demo's way, silent and traceback write failures, a step-1 size
that was not said, names given twice, the option named in mask errors, a 0/255 start mask,
frames the preview cannot draw, a folder as the mask, and numbers OpenCV or int() refuse."""

from __future__ import annotations

import argparse
from collections.abc import Callable
import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from cva_confidence_ros.demo import _check_args, _match_all
from cva_confidence_ros.demo import main as demo_main
from cva_confidence_ros.errors import ConfigError, DataError
from cva_confidence_ros.mask import load_mask
from msg_tools.mask_tool import draw_mask
from msg_tools.mask_tool import main as mask_main


def _demo_exit_code(argv: list[str]) -> int:
    try:
        return demo_main(argv)
    except SystemExit as exc:  # argparse's error exit
        return int(exc.code or 0)


def _make_file(path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text('in the way')


def _make_link(path: Path) -> None:
    target = path.parent / 'elsewhere'
    target.mkdir(parents=True)
    os.symlink(target, path)


def _make_folder(path: Path) -> None:
    path.mkdir(parents=True)


@pytest.mark.timeout(120)
@pytest.mark.parametrize(
    ('name', 'make', 'message'),
    [
        ('motorcycle_bag', _make_file, 'motorcycle_bag is a file, where the demo writes a folder'),
        ('motorcycle_bag', _make_link, 'motorcycle_bag is a link, where the demo writes a folder'),
        ('replay/census_bm__pkrn', _make_file, 'census_bm__pkrn is a file, where the demo'),
        ('replay', _make_file, 'replay is a file, where the demo writes a folder'),
        ('disparity_census_bm.png', _make_folder, 'disparity_census_bm.png is a folder, where'),
        ('cost_volume_summary.json', _make_folder, 'cost_volume_summary.json is a folder'),
    ],
)
def test_what_is_in_the_demos_way_is_refused_before_step_1(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str,
    make: Callable[[Path], None], message: str,
) -> None:
    # Was a NotADirectoryError traceback from shutil.rmtree after steps 1 and 2 (a file or link
    # where the bag or a replay folder goes), or a disparity PNG silently not written (and
    # still listed in cost_volume_summary.json), or an IsADirectoryError traceback.
    out = tmp_path / 'demo'
    make(out / name)
    code = _demo_exit_code(['--out', str(out), '--matchers', 'census_bm', '--methods', 'pkrn'])
    assert code == 2
    err = capsys.readouterr().err
    assert message in err.splitlines()[-1] and 'Traceback' not in err
    assert '[demo] step' not in err and not (out / 'left.png').exists()


@pytest.mark.parametrize('name', ['disparity_census_bm.png', 'cost_volume_summary.json'])
def test_step_1_outputs_that_cannot_be_written_are_an_error(tmp_path: Path, name: str) -> None:
    # cv2.imwrite only returns False: the PNG was missing without a word; the JSON raised a
    # bare OSError (a traceback out of cva-demo).
    (tmp_path / name).mkdir()
    with pytest.raises(DataError, match=f'cannot write .*{name}'):
        _match_all(tmp_path, ['census_bm'], 64, 4)


def test_a_full_disk_in_step_1_is_an_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    file_size_limit: Callable[[int], Any],
) -> None:
    monkeypatch.setattr('cva_confidence_ros.demo._log', lambda message: None)
    with file_size_limit(2000), pytest.raises(DataError, match='cannot write .*disparity_'):
        _match_all(tmp_path, ['census_bm'], 64, 4)


def test_step_1_says_when_it_matches_at_a_smaller_size(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # At D = 8 the ground truth (≈ 15 px at 1/4) only fits at 1/16: step 1 said "at 1/4 size"
    # and matched a 46×31 pair without a word.
    rows = _match_all(tmp_path, ['census_bm'], 8, 4)
    assert rows[0]['shape'] == [8, 31, 46]
    err = capsys.readouterr().err
    assert 'does not fit into D = 8 at 1/4 size: matching at 1/16 (46×31 px) instead' in err
    _match_all(tmp_path, ['census_bm'], 64, 4)
    assert 'does not fit' not in capsys.readouterr().err


def test_a_name_given_twice_is_run_once(tmp_path: Path) -> None:
    # Was matched and replayed twice, with the same row twice in the table.
    args = argparse.Namespace(
        downsample=4, max_disparity=64, matchers='census_bm, census_bm,',
        methods='pkrn,score,pkrn', out=tmp_path / 'demo',
    )
    assert _check_args(args) == (['census_bm'], ['pkrn', 'score'])


def test_mask_errors_name_the_option_that_gave_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    missing = tmp_path / 'missing.png'
    with pytest.raises(ConfigError, match=f"^mask_path '{missing}' is not a file$"):
        load_mask(missing)  # the node's parameter, as before
    with pytest.raises(ConfigError, match=f"^--start '{missing}' is not a file$"):
        load_mask(missing, '--start')
    # cva-mask said "mask_path", which it has no option of.
    assert mask_main([str(tmp_path / 'out.png'), '--start', str(missing)]) == 2
    assert capsys.readouterr().err.strip() == f"cva-mask: error: --start '{missing}' is not a file"


def test_a_0_255_start_mask_comes_back_as_bool() -> None:
    # A uint8 start stayed uint8, and `&=` with the polygon made its 255s into 1s: ~keep was
    # then nonzero everywhere (100 % ignored) instead of the triangle.
    start = np.full((6, 8), 255, np.uint8)
    triangle = np.array([[0, 0], [3, 0], [0, 3]], np.int32)
    keep = draw_mask(8, 6, start=start, polygons=[triangle])
    assert keep.dtype == bool
    np.testing.assert_array_equal(keep, draw_mask(8, 6, start=start > 0, polygons=[triangle]))
    assert np.count_nonzero(~keep) == 10
    assert start.min() == 255  # not drawn on


def test_a_frame_of_another_dtype_is_named_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A float32 TIFF: the mask was written, then the preview failed with "left and right must
    # both be 8-bit or both 16-bit" (exit 2, a mask on disk all the same).
    image = tmp_path / 'frame.tiff'
    assert cv2.imwrite(str(image), np.full((20, 24), 0.5, np.float32))
    out = tmp_path / 'mask.png'
    assert mask_main([str(out), '--image', str(image), '--below', '10']) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f'cva-mask: error: --image {image} is a float32 image; expected an 8- or '
                   '16-bit camera frame')
    assert not out.exists() and not (tmp_path / 'mask_preview.png').exists()
    # A 16-bit frame (12 bits used) is drawn on, scaled as the node scales it.
    deep = tmp_path / 'deep.png'
    assert cv2.imwrite(str(deep), np.tile(np.linspace(0, 4095, 24).astype(np.uint16), (20, 1)))
    assert mask_main([str(out), '--image', str(deep), '--below', '10']) == 0
    shown = cv2.imread(str(tmp_path / 'mask_preview.png'))
    assert shown.shape == (20, 24, 3) and shown[0, -1].min() == 255


@pytest.mark.parametrize('overwrite', [[], ['--overwrite']])
def test_a_folder_as_the_mask_is_named_as_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], overwrite: list[str]
) -> None:
    # Without --overwrite it said "exists already; use --overwrite to replace it", and with
    # it that the path is a folder.
    out = tmp_path / 'mask.png'
    out.mkdir()
    assert mask_main([str(out), '--size', '8x6', '--below', '3', *overwrite]) == 2
    assert capsys.readouterr().err.strip() == (
        f'cva-mask: error: out {out} is a folder; expected a file path'
    )
    assert out.is_dir()


@pytest.mark.parametrize(
    ('extra', 'message'),
    [
        (['--size', '4²x3'], "--size must be WIDTHxHEIGHT in pixels, e.g. 640x480; got '4²x3'"),
        (['--size', '8x6', '--polygon', '0,0', '99999999999,0', '0,5'],
         "--polygon corners must lie within ±2147483647 px; got '99999999999,0'"),
    ],
)
def test_numbers_int_or_opencv_refuse_are_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], message: str
) -> None:
    # Were a ValueError (int('4²'), though '4²'.isdigit()) and an OverflowError (an int32
    # corner for OpenCV) with tracebacks.
    out = tmp_path / 'mask.png'
    assert mask_main([str(out), *extra]) == 2
    assert capsys.readouterr().err.strip() == f'cva-mask: error: {message}'
    assert not out.exists()


def test_ctrl_c_in_step_1_exits_130(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # A KeyboardInterrupt traceback; steps 2 and 3 (the bag tools) answer 130.
    import cva_confidence_ros.demo as demo

    def interrupted(*args: Any, **kwargs: Any) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(demo, '_match_all', interrupted)
    assert demo_main(['--out', str(tmp_path / 'demo'), '--matchers', 'census_bm',
                      '--methods', 'mlm']) == 130
    assert 'cva-demo: interrupted in step 1' in capsys.readouterr().err


def test_bag_replay_mask_errors_name_its_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # cva-bag-replay --mask missing.png said "mask_path '…' is not a file".
    from msg_tools.bag_replay import main as replay_main

    missing = tmp_path / 'missing.png'
    assert replay_main([str(tmp_path / 'bag'), '--out', str(tmp_path / 'out'), '--report',
                        str(tmp_path / 'report'),
                        '--mask', str(missing)]) == 2
    err = capsys.readouterr().err
    assert f"--mask '{missing}' is not a file" in err, err
