"""Review 28 of the point-cloud filter and the image transports: each test a regression test of
a fault found in the review (the cloud filter node and its entry point: none found)."""

from __future__ import annotations

import re
import warnings

import cv2
import numpy as np
import pytest
from sensor_msgs.msg import CompressedImage, Image
from std_msgs.msg import Header

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.ros.convert import depth_to_image
from cva_confidence_ros.ros.transport import (
    COMPRESSED_DEPTH_HEADER,
    compressed_depth_to_array,
    compressed_depth_values,
    depth_image_to_compressed_depth,
    rgb_to_compressed,
)

_DEPTH = np.array([[0.5, 1.0, 5.0, np.nan]], dtype=np.float32)


def _codes(msg: CompressedImage) -> np.ndarray:
    codes = cv2.imdecode(np.frombuffer(bytes(msg.data)[12:], np.uint8), cv2.IMREAD_UNCHANGED)
    assert codes is not None
    return codes


@pytest.mark.parametrize('depth_max', [70.0, 1e300, 1e306])
def test_16uc1_depth_max_beyond_16_bits_cuts_nothing(depth_max: float) -> None:
    # int(depth_max * 1000) overflowed a float32 cast (a warning) from 3.4e35 m and raised
    # OverflowError from 1.8e305 m (depth_max * 1000 = inf): a finite depth_max the node's
    # compressed_depth_max accepts.
    millimetres = np.array([[1, 500, 65534, 65535, 0]], dtype=np.uint16)
    image = Image(
        height=1, width=5, encoding='16UC1', is_bigendian=False, step=10,
        data=millimetres.tobytes(),
    )  # fmt: skip
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        msg = depth_image_to_compressed_depth(image, depth_max=depth_max)
    np.testing.assert_array_equal(_codes(msg), millimetres)


@pytest.mark.parametrize(
    ('quantization', 'depth_max'),
    [
        (2e19, 10.0),  # A = Q·(Q + 1) overflows float32: inf in the header, NaN codes
        (100.0, 1e-50),  # A / depth_max overflows: B = −inf
        (1e-46, 10.0),  # Q is 0 in float32: A = 0, every depth decoded as 0
        (1.0, 1e30),  # B rounds to 1: code 1 decoded as an infinite depth
    ],
)
def test_quantisation_that_float32_cannot_hold_is_refused(
    quantization: float, depth_max: float
) -> None:
    message = 'a compressedDepth header needs a finite A > 0 and B < 1'
    with pytest.raises(InputError, match=re.escape(message)):
        compressed_depth_values(_DEPTH, depth_max, quantization)
    with pytest.raises(InputError, match=re.escape(message)):
        depth_image_to_compressed_depth(
            depth_to_image(_DEPTH, Header(), '32FC1'), depth_max, quantization
        )


def test_a_parameter_that_is_no_number_is_an_input_error() -> None:
    # Was a TypeError out of np.isfinite, which the docstring does not name.
    for call in (
        lambda: compressed_depth_values(_DEPTH, depth_max='10'),  # type: ignore[arg-type]
        lambda: compressed_depth_values(_DEPTH, depth_quantization=None),  # type: ignore[arg-type]
        lambda: depth_image_to_compressed_depth(
            depth_to_image(_DEPTH, Header(), '16UC1'),
            depth_max='10',  # type: ignore[arg-type]
        ),
    ):
        with pytest.raises(InputError, match='must be a positive number'):
            call()


@pytest.mark.parametrize(
    ('a', 'b'),
    [
        (-10100.0, -1009.0),  # negative depths
        (10100.0, 1e5),  # B above every code: negative depths
        (float('inf'), -1009.0),  # infinite depths
        (float('nan'), 0.0),  # NaN everywhere, no error
        (0.0, 0.0),  # a 16UC1 header on a 32FC1 image: every depth 0
    ],
)
def test_32fc1_header_that_gives_no_positive_depth_is_refused(a: float, b: float) -> None:
    good = depth_image_to_compressed_depth(depth_to_image(_DEPTH, Header(), '32FC1'))
    corrupt = CompressedImage(
        format=good.format, data=COMPRESSED_DEPTH_HEADER.pack(0, a, b) + bytes(good.data)[12:]
    )
    with pytest.raises(InputError, match=re.escape('a 32FC1 one needs a finite A > 0 and B < 1')):
        compressed_depth_to_array(corrupt)


def test_16uc1_header_is_not_read() -> None:
    # The C++ plugin leaves depthParam unset for 16UC1 (this module writes zeros): any header
    # decodes there.
    good = depth_image_to_compressed_depth(depth_to_image(_DEPTH, Header(), '16UC1'))
    data = COMPRESSED_DEPTH_HEADER.pack(0, float('nan'), -5.0) + bytes(good.data)[12:]
    back = compressed_depth_to_array(CompressedImage(format=good.format, data=data))
    np.testing.assert_allclose(back, _DEPTH)


@pytest.mark.parametrize('shape', [(0, 4, 3), (4, 0, 3)])
def test_an_empty_overlay_is_an_input_error(shape: tuple[int, int, int]) -> None:
    # Was OpenCV's cv2.error out of cvtColor, outside the package's exception tree.
    with pytest.raises(InputError, match=re.escape('H and W > 0')):
        rgb_to_compressed(np.zeros(shape, np.uint8), Header())


def test_node_config_refuses_a_quantisation_float32_cannot_hold() -> None:
    # Each frame was dropped (InputError) once a compressedDepth subscriber came; now the
    # configuration is refused at start-up. 16UC1 does not use the quantisation.
    from cva_confidence_ros.errors import ConfigError
    from cva_confidence_ros.ros.params import NodeConfig

    with pytest.raises(ConfigError, match=r'^compressed_depth_quantization and '
                                          r'compressed_depth_max: depth_quantization 2e\+19'):
        NodeConfig(compressed_depth_quantization=2e19)
    NodeConfig(compressed_depth_quantization=2e19, depth_encoding='16UC1')
    NodeConfig()
