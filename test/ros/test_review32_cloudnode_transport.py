"""Review 32: ``ros.transport`` refuses a compressedDepth format naming another compression
and says what is wrong with an overlay that is no numpy array."""

from __future__ import annotations

import numpy as np
import pytest
from sensor_msgs.msg import CompressedImage
from std_msgs.msg import Header

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.ros.convert import depth_to_image
from cva_confidence_ros.ros.transport import (
    compressed_depth_to_array,
    depth_image_to_compressed_depth,
    rgb_to_compressed,
)


def _depth_message() -> CompressedImage:
    depth = np.array([[0.5, 1.0], [np.nan, 2.0]], np.float32)
    return depth_image_to_compressed_depth(depth_to_image(depth, Header(frame_id='cam')))


@pytest.mark.parametrize('compression', ['jpeg', 'tiff', 'png2'])
def test_compressed_depth_naming_another_compression_is_refused(compression: str) -> None:
    # 'compressedDepth jpeg' (which the C++ plugin refuses as unsupported) was decoded as if
    # it said png. png, and the older formats that name no compression, still decode.
    msg = _depth_message()
    for fmt in ('32FC1; compressedDepth png', '32FC1; compressedDepth PNG',
                '32FC1; compressedDepth', '32FC1'):
        msg.format = fmt
        depth = compressed_depth_to_array(msg)
        assert np.isnan(depth[1, 0])
        np.testing.assert_allclose(depth[0], [0.5, 1.0], rtol=1e-3)
    msg.format = f'32FC1; compressedDepth {compression}'
    with pytest.raises(InputError, match=f"compression '{compression}' is not supported"):
        compressed_depth_to_array(msg)


def test_rgb_to_compressed_refuses_a_list_with_an_input_error() -> None:
    # A nested list raised AttributeError: 'list' object has no attribute 'ndim'.
    with pytest.raises(InputError, match='numpy array; got list'):
        rgb_to_compressed([[[1, 2, 3]]], Header())  # type: ignore[arg-type]
