"""Review 31: ignore masks, ``cva-mask``, progress lines, output checks and registries."""

from __future__ import annotations

import io
from pathlib import Path

import cv2
import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.mask import load_mask
from cva_confidence_ros.outputs import check_output_dir, check_output_file
from cva_confidence_ros.registry import Registry
from msg_tools.mask_tool import _parse_polygon, draw_mask, main
from msg_tools.progress import Progress


def test_progress_with_no_time_elapsed_tells_no_rate() -> None:
    # A coarse clock (or a first frame within its tick) used to give 1e9 fps and "~0 s left".
    stream = io.StringIO()
    progress = Progress(10, prefix='p: ', stream=stream, clock=lambda: 5.0)
    progress.update()
    assert stream.getvalue() == 'p: 1/10 frames, ? fps\n'
    unknown = Progress(0, stream=io.StringIO(), clock=lambda: 5.0)
    unknown.update()
    assert unknown.line() == '1/? frames, ? fps'


def test_a_float_mask_holding_nan_is_refused(tmp_path: Path) -> None:
    # NaN != 0 made those pixels judged, though a NaN rather marks "no value".
    values = np.ones((6, 8), dtype=np.float32)
    values[:2] = np.nan
    values[5] = 0.0
    path = tmp_path / 'mask.tiff'
    assert cv2.imwrite(str(path), values)
    with pytest.raises(ConfigError, match=r"--mask '.*mask\.tiff' holds 16 NaN values"):
        load_mask(path, '--mask')
    values[:2] = 1.0  # a float mask without NaN still loads
    assert cv2.imwrite(str(path), values)
    keep = load_mask(path)
    assert keep[:5].all() and not keep[5].any()


def test_an_unhashable_name_is_an_unknown_one() -> None:
    # A list (e.g. from a YAML file) raised TypeError "unhashable type: 'list'".
    registry: Registry[int] = Registry('matcher')
    registry.add('census', 1)
    with pytest.raises(ConfigError, match=r"unknown matcher \['census'\]; expected one of "
                                          r"\['census'\]"):
        registry.get(['census'])  # type: ignore[arg-type]
    assert ['census'] not in registry
    assert 'census' in registry


@pytest.mark.parametrize('check', [check_output_file, check_output_dir])
def test_a_place_where_no_byte_can_be_written_is_refused(
    tmp_path: Path, file_size_limit, check
) -> None:
    # The probe made an empty file only, which a full disk or quota still allows: the job
    # found out after its hour. A file size limit of 0 refuses writes the same way (EFBIG
    # instead of ENOSPC) while files can still be made.
    with file_size_limit(0), pytest.raises(ConfigError) as caught:
        check(tmp_path / 'out', '--out')
    assert 'cannot write in' in str(caught.value) and 'File too large' in str(caught.value)
    assert not [p for p in tmp_path.rglob('*') if p.is_file()]  # no probe left behind


def test_a_polygon_off_the_image_is_refused_as_a_rectangle_is(tmp_path: Path, capsys) -> None:
    # It used to ignore nothing, silently (a rectangle off the image is refused).
    off = _parse_polygon(['100,10', '120,10', '110,30'])
    with pytest.raises(ConfigError, match=r'--polygon 100,10 120,10 110,30 covers no pixel of '
                                          r'the 64×48 image'):
        draw_mask(64, 48, polygons=[_parse_polygon(['0,0', '5,0', '0,5']), off])
    out = tmp_path / 'mask.png'
    assert main([str(out), '--size', '64x48', '--polygon', '10,100', '30,100', '20,120']) == 2
    assert 'covers no pixel' in capsys.readouterr().err
    assert not out.exists()
    # partly inside: clipped, as before
    keep = draw_mask(64, 48, polygons=[_parse_polygon(['60,0', '100,0', '60,40'])])
    assert not keep[0, 63] and keep[0, 59] and not keep.all()


@pytest.mark.parametrize('extra', [['--frame', '3'], ['--topic', '/left/image_raw']])
def test_frame_and_topic_without_a_bag_are_refused(
    tmp_path: Path, capsys, extra: list[str]
) -> None:
    # They were silently ignored with --size or --image.
    image = tmp_path / 'frame.png'
    cv2.imwrite(str(image), np.full((12, 16), 90, dtype=np.uint8))
    out = tmp_path / 'mask.png'
    for source in (['--size', '16x12'], ['--image', str(image)]):
        assert main([str(out), *source, '--rect', '0', '0', '4', '4', *extra]) == 2
        err = capsys.readouterr().err
        assert f'{extra[0]} {extra[1]} picks a message of --bag' in err
        assert not out.exists()
    assert main([str(out), '--size', '16x12', '--rect', '0', '0', '4', '4']) == 0
