"""Review 31: the PNG header of ``compressedDepth`` payloads (ros/transport.py) and
``cva-lifecycle``'s checks of its own arguments (ros/lifecycle_cli.py)."""

from __future__ import annotations

import os
import re
import struct
import subprocess
import sys
import textwrap
import zlib

import cv2
import numpy as np
import pytest
from sensor_msgs.msg import CompressedImage

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.ros import lifecycle_cli, transport
from cva_confidence_ros.ros.transport import COMPRESSED_DEPTH_HEADER, compressed_depth_to_array

pytestmark = pytest.mark.timeout(60)

_HEADER = COMPRESSED_DEPTH_HEADER.pack(0, 10100.0, -1009.0)  # Q = 100, depth_max = 10 m


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack('>I', len(body)) + kind + body + struct.pack('>I', zlib.crc32(kind + body))


def _png(width: int, height: int, bit_depth: int = 16, colour_type: int = 0,
         rows: int = 1) -> bytes:
    """A PNG whose IHDR names ``width``×``height``, with ``rows`` rows of zeros (one byte per
    sample is enough: none of these is meant to decode in full)."""
    ihdr = struct.pack('>IIBBBBB', width, height, bit_depth, colour_type, 0, 0, 0)
    packer = zlib.compressobj(9)
    row = bytes(1 + (width * bit_depth * (3 if colour_type == 2 else 1) + 7) // 8)
    body = b''.join(packer.compress(row) for _ in range(rows)) + packer.flush()
    palette = _chunk(b'PLTE', bytes(6)) if colour_type == 3 else b''
    return (b'\x89PNG\r\n\x1a\n' + _chunk(b'IHDR', ihdr) + palette + _chunk(b'IDAT', body)
            + _chunk(b'IEND', b''))


def _message(payload: bytes) -> CompressedImage:
    return CompressedImage(format='32FC1; compressedDepth png', data=_HEADER + payload)


@pytest.fixture
def no_decoding(monkeypatch: pytest.MonkeyPatch) -> None:
    """cv2.imdecode fails the test: the payload must be refused from its header alone."""
    def imdecode(*args: object) -> None:
        raise AssertionError('cv2.imdecode was called: the header was not checked first')

    monkeypatch.setattr(cv2, 'imdecode', imdecode)


# transport.py -------------------------------------------------------------------------------


def test_a_png_header_naming_too_many_pixels_is_refused_before_decoding(no_decoding) -> None:
    # A 130-byte message naming 20000 × 20000 16-bit pixels (under OpenCV's own 2**30): OpenCV
    # reserved 800 MB for it before failing on the missing rows; with the rows (777 kB of
    # zlib) it decoded, 2.7 GB peak and 11 s.
    msg = _message(_png(20000, 20000))
    assert len(msg.data) < 200
    with pytest.raises(InputError, match='at most 33554432 pixels: its header names '
                                         '20000×20000 = 400000000'):
        compressed_depth_to_array(msg)


@pytest.mark.parametrize(
    ('bit_depth', 'colour_type', 'named'),
    [(1, 3, '1-bit palette'), (8, 0, '8-bit gray'), (16, 2, '16-bit RGB'),
     (16, 4, '16-bit gray + alpha')],
)
def test_a_png_of_another_depth_or_colour_type_is_refused_before_decoding(
    no_decoding, bit_depth: int, colour_type: int, named: str
) -> None:
    # A 48.7 kB 1-bit palette PNG of 20000 × 20000 was expanded to 1.2 GB of BGR (2.3 GB peak)
    # before the check after decoding refused it.
    expected = f'not a one-channel 16-bit PNG ({named}, 40×30)'
    with pytest.raises(InputError, match=re.escape(expected)):
        compressed_depth_to_array(_message(_png(40, 30, bit_depth, colour_type)))


@pytest.mark.parametrize('payload', [b'P5 3 2 65535\n' + bytes(range(12)), b'not a png at all'],
                         ids=['pgm', 'text'])
def test_a_payload_in_another_image_format_is_refused(payload: bytes) -> None:
    # A 16-bit PGM decoded as a 3 × 2 depth map: OpenCV reads any format by its signature,
    # and the PNG header check must not be bypassed by another format's header.
    with pytest.raises(InputError, match='does not start with the PNG signature .*; it is not '
                                         'a one-channel 16-bit PNG'):
        compressed_depth_to_array(_message(payload))


def test_the_bound_is_a_parameter_and_a_good_png_still_decodes() -> None:
    ok, png = cv2.imencode('.png', np.array([[1, 2, 3], [0, 5, 6]], np.uint16))
    assert ok
    msg = _message(png.tobytes())
    depth = compressed_depth_to_array(msg, max_pixels=6)
    assert depth.shape == (2, 3) and np.isnan(depth[1, 0]) and np.isfinite(depth[0]).all()
    with pytest.raises(InputError, match='at most 5 pixels: its header names 3×2 = 6'):
        compressed_depth_to_array(msg, max_pixels=5)
    for bad in (0, -1, 2.5, True, None):
        with pytest.raises(InputError, match='max_pixels must be a positive integer'):
            compressed_depth_to_array(msg, max_pixels=bad)  # type: ignore[arg-type]
    assert transport.png_header(png.tobytes()) == (3, 2, 16, 0)


@pytest.mark.parametrize(
    ('data', 'message'),
    [
        (b'\x89PNG\r\n\x1a\n' + bytes(10), 'too short for a PNG header'),
        (b'\x89PNG\r\n\x1a\n' + _chunk(b'IDAT', bytes(13)), 'does not begin with a 13-byte IHDR'),
        (_png(0, 5), 'names an empty 0×5 image'),
    ],
    ids=['short', 'no-ihdr', 'empty'],
)
def test_png_header_names_what_is_wrong(data: bytes, message: str) -> None:
    with pytest.raises(InputError, match=message):
        transport.png_header(data, 'payload')


def test_peak_memory_of_a_large_png_header_stays_small() -> None:
    # In a child, so that the peak is this decode's: a 6000 × 6000 16-bit PNG of 70 kB (36 M
    # pixels, over the default bound) decoded, +259 MB (the codes and the float32 depths).
    # VmHWM, not ru_maxrss: that one keeps the forking parent's size across exec.
    script = textwrap.dedent("""
        import sys
        from sensor_msgs.msg import CompressedImage
        from cva_confidence_ros.errors import InputError
        from cva_confidence_ros.ros.transport import compressed_depth_to_array
        def peak_mb():
            with open('/proc/self/status') as status:
                line = next(line for line in status if line.startswith('VmHWM:'))
            return int(line.split()[1]) // 1024
        import cv2  # its own memory before the baseline
        data = sys.stdin.buffer.read()
        msg = CompressedImage(format='32FC1; compressedDepth png', data=data)
        before = peak_mb()
        try:
            compressed_depth_to_array(msg)
            print('decoded')
        except InputError:
            print('refused')
        print(peak_mb() - before)
    """)
    data = _HEADER + _png(6000, 6000, rows=6000)
    assert len(data) < 100_000
    done = subprocess.run(
        [sys.executable, '-c', script], input=data, capture_output=True, timeout=50,
        env={**os.environ, 'OMP_NUM_THREADS': '1'}, check=True,
    )
    outcome, grown_mb = done.stdout.decode().split()
    assert outcome == 'refused' and int(grown_mb) < 50, (outcome, grown_mb)


# lifecycle_cli.py ---------------------------------------------------------------------------


def test_cva_lifecycle_refuses_a_nan_timeout(capsys: pytest.CaptureFixture[str]) -> None:
    # nan passed the "<= 0" check: no wait at all, then "no answer ... within nan s".
    assert lifecycle_cli.main(['--timeout', 'nan', 'get', '/review31_absent']) == 2
    assert 'cva-lifecycle: --timeout must be > 0 s; got nan' in capsys.readouterr().err


def test_cva_lifecycle_names_a_bad_node_name(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # Was rclpy's InvalidServiceNameException out of create_client: a traceback and exit
    # status 1, the status of a refused transition.
    for name, why in [('bad-name', 'other than alphanumerics'), ('', 'must not be empty'),
                      ('/ns//x', "must not end with a '/'"), ('/x y', 'other than alphanumerics')]:
        code = lifecycle_cli.main(['--timeout', '1', 'get', name])
        err = capsys.readouterr().err
        assert code == lifecycle_cli.EXIT_NO_ANSWER, name
        assert f'cva-lifecycle: {name!r} is not a node name (' in err and why in err, err
    # A relative name with a namespace stays a node name (asked for, not answered here).
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    monkeypatch.setenv('ROS_DOMAIN_ID', str(221 + os.getpid() % 12))
    name = f'review31/absent_{os.getpid()}'
    assert lifecycle_cli.main(['--timeout', '0.3', 'set', name, 'configure']) == 2
    assert f'no answer from /{name}/change_state within 0.3 s' in capsys.readouterr().err
