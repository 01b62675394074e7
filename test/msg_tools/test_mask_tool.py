"""``cva-mask``: ignore masks drawn from the command line, on real rosbag2 frames."""

from __future__ import annotations

from pathlib import Path
import re

import cv2
from msg_test_utils import START_NS, textured_pair, write_stereo_bag
import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.mask import load_mask
from msg_tools.bagio import OutputBag
from msg_tools.convert import IMAGE, image_to_msg, jazzy_typestore
from msg_tools.mask_tool import draw_mask, main


def _left_frames(count: int = 2) -> list[dict[str, object]]:
    pairs = (textured_pair(30, 40, 4, seed) for seed in range(count))
    return [{'left': left, 'right': right} for left, right in pairs]


def test_rectangles_polygons_and_rows_on_a_bag_frame(tmp_path: Path, capsys) -> None:
    frames = _left_frames()
    bag = write_stereo_bag(tmp_path / 'bag', frames)
    out = tmp_path / 'masks' / 'robot.png'
    code = main([str(out), '--bag', str(bag), '--frame', '1', '--below', '25',
                 '--rect', '35', '-5', '99', '5', '--polygon', '0,10', '10,24', '0,24'])
    assert code == 0
    keep = load_mask(out)
    assert keep.shape == (30, 40)
    assert not keep[25:].any() and keep[:25].any()
    assert not keep[:5, 35:].any() and keep[5, 35] and keep[0, 34]  # clipped to the image
    assert not keep[20, 0] and not keep[24, 10] and keep[10, 20]  # the polygon, edges included
    printed = capsys.readouterr().out
    assert 'robot.png: 40×30 px' in printed
    assert 'rows 0 to 24 processed, 5 of 30 skipped' in printed
    assert 'mask_path:=' in printed
    # The preview is the bag's frame 1, shaded red where ignored.
    preview = cv2.cvtColor(cv2.imread(str(tmp_path / 'masks' / 'robot_preview.png')),
                           cv2.COLOR_BGR2RGB)
    left = frames[1]['left']
    assert preview.shape == (30, 40, 3)
    np.testing.assert_array_equal(preview[10, 20], np.repeat(left[10, 20], 3))
    shaded = preview[27, 20].astype(int)
    assert shaded[0] > shaded[1] and shaded[0] > shaded[2]
    assert (preview[25] == (255, 220, 0)).all()  # the first row not processed


def test_compressed_bags_an_image_and_adding_to_a_mask(tmp_path: Path) -> None:
    frames = [{**frame, 'transport': 'png'} for frame in _left_frames(1)]
    bag = write_stereo_bag(tmp_path / 'bag', frames)
    out = tmp_path / 'mask.png'
    assert main([str(out), '--bag', str(bag), '--rect', '0', '0', '4', '4']) == 0
    assert load_mask(out).shape == (30, 40) and not load_mask(out)[:4, :4].any()
    # Nothing already written is replaced without --overwrite.
    before = out.read_bytes()
    assert main([str(out), '--start', str(out), '--rect', '36', '0', '40', '4']) == 2
    assert out.read_bytes() == before
    assert main([str(out), '--start', str(out), '--rect', '36', '0', '40', '4',
                 '--overwrite']) == 0
    keep = load_mask(out)
    assert not keep[:4, :4].any() and not keep[:4, 36:].any() and keep[10:].all()
    image = tmp_path / 'frame.png'
    cv2.imwrite(str(image), np.full((20, 24, 3), 90, np.uint8))
    assert main([str(tmp_path / 'small.png'), '--image', str(image), '--above', '3']) == 0
    assert load_mask(tmp_path / 'small.png').shape == (20, 24)
    assert (tmp_path / 'small_preview.png').is_file()
    assert main([str(tmp_path / 'sized.png'), '--size', '64x48', '--below', '40']) == 0
    assert load_mask(tmp_path / 'sized.png').shape == (48, 64)
    assert not (tmp_path / 'sized_preview.png').exists()  # no frame, no preview


@pytest.mark.parametrize(
    ('extra', 'message'),
    [
        (['--size', '64by48'], '--size must be WIDTHxHEIGHT'),
        (['--size', '64x48', '--rect', '70', '0', '80', '10'], 'covers no pixel of the 64×48'),
        (['--size', '64x48', '--polygon', '1,1', '5,5'], '--polygon needs 3 corners'),
        (['--size', '64x48', '--polygon', '1,1', '5;5', '3,3'], 'corners must be X,Y'),
        (['--size', '64x48', '--below', '60'], '--below must be a row in \\[0, 48\\]'),
        (['--size', '64x48', '--below', '0'], 'would ignore every pixel'),
        (['--size', '64x48', '--preview', 'p.png'], '--preview needs a frame'),
        (['--bag', 'BAG', '--frame', '7'], 'has no message 7 on /left/image_rect'),
        (['--bag', 'BAG', '--topic', '/camera/left'], "no image topic '/camera/left'; image "
                                                      "topics: \\['/left/image_rect'"),
        ([], 'give the size'),
    ],
)
def test_mistakes_are_named_and_write_nothing(
    tmp_path: Path, capsys, extra: list[str], message: str
) -> None:
    bag = write_stereo_bag(tmp_path / 'bag', _left_frames(1))
    out = tmp_path / 'mask.png'
    argv = [str(out), *[str(bag) if item == 'BAG' else item for item in extra]]
    assert main(argv) == 2
    assert re.search(message, capsys.readouterr().err)
    assert not out.exists()


def test_a_corrupt_message_in_the_bag_is_named(tmp_path: Path, capsys) -> None:
    # Messages 1 and 2 are cut short (a bad sequence length; no room for the header's stamp):
    # a one-line error naming the message and the topic, no rosbags traceback.
    store = jazzy_typestore()
    bag_path = tmp_path / 'bag'
    with OutputBag(bag_path, 'mcap', store) as bag:
        for index, cut in enumerate((None, 60, 10)):
            left = textured_pair(30, 40, 4, index)[0]
            data = bytes(store.serialize_cdr(
                image_to_msg(left, START_NS + index, 'l', store), IMAGE
            ))
            bag.write('/left/image_rect', IMAGE, data[:cut], START_NS + index)
    out = tmp_path / 'mask.png'
    for frame in (1, 2):
        assert main([str(out), '--bag', str(bag_path), '--frame', str(frame)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(
            f'cva-mask: error: message {frame} on /left/image_rect of bag {bag_path} cannot be '
            f'read as a sensor_msgs/msg/Image (corrupt or truncated?): SerdeError: '
        )
        assert len(err.strip().splitlines()) == 1 and 'Traceback' not in err
        assert not out.exists()
    # The intact message before them still gives a mask.
    assert main([str(out), '--bag', str(bag_path), '--frame', '0', '--below', '25']) == 0
    assert load_mask(out).shape == (30, 40)


def test_a_preview_onto_the_mask_itself_is_refused(tmp_path: Path, capsys) -> None:
    image = tmp_path / 'frame.png'
    cv2.imwrite(str(image), _left_frames(1)[0]['left'])
    out = tmp_path / 'mask.png'
    assert main([str(out), '--image', str(image), '--below', '20']) == 0
    before = out.read_bytes()
    capsys.readouterr()
    # Spelt another way, it is still the same file.
    same = tmp_path / 'sub' / '..' / 'mask.png'
    code = main([str(out), '--image', str(image), '--below', '10', '--preview', str(same),
                 '--overwrite'])
    assert code == 2
    assert capsys.readouterr().err.strip() == (
        f'cva-mask: error: --preview {same} is the mask {out} itself: the preview would '
        'replace the mask; give the preview another name'
    )
    assert out.read_bytes() == before
    assert load_mask(out)[20:].sum() == 0


def test_draw_mask_refuses_a_start_mask_of_another_size() -> None:
    with pytest.raises(ConfigError, match='start mask is 4×3 px, not 5×3'):
        draw_mask(5, 3, start=np.ones((3, 4), bool))


def test_a_preview_left_from_an_earlier_mask_is_pointed_out(tmp_path: Path, capsys) -> None:
    out = tmp_path / 'mask.png'
    image = tmp_path / 'frame.png'
    cv2.imwrite(str(image), np.full((20, 24, 3), 90, np.uint8))
    assert main([str(out), '--image', str(image), '--rect', '0', '0', '4', '4']) == 0
    preview = tmp_path / 'mask_preview.png'
    drawn = preview.read_bytes()
    assert 'note' not in capsys.readouterr().err
    # Added to without a frame: the old preview no longer shows the mask, and is left alone.
    assert main([str(out), '--start', str(out), '--rect', '20', '0', '24', '4',
                 '--overwrite']) == 0
    err = capsys.readouterr().err
    assert f'cva-mask: note: {preview} still shows the previous mask' in err
    assert preview.read_bytes() == drawn
    # Drawn again with the frame: no note.
    assert main([str(out), '--start', str(out), '--image', str(image), '--overwrite']) == 0
    assert 'note' not in capsys.readouterr().err
    assert preview.read_bytes() != drawn
