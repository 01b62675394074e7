"""Hostile files given to the msg_tools commands: a frame for ``cva-mask --image`` that declares
far more pixels than it holds is refused before it is decoded."""

from __future__ import annotations

from pathlib import Path
import struct
import zlib

import cv2
import numpy as np
import pytest

from msg_tools.mask_tool import main


def _chunk(kind: bytes, data: bytes) -> bytes:
    crc = zlib.crc32(kind + data) & 0xFFFFFFFF
    return struct.pack('>I', len(data)) + kind + data + struct.pack('>I', crc)


def test_cva_mask_refuses_an_image_bomb_without_decoding_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # 8-bit grey, 30000 × 30000, one row of data: ~100 bytes that cv2.imread allocated 900 MB
    # for (a complete one of 2.6 MB decodes to 2.7 GB in colour).
    ihdr = struct.pack('>IIBBBBB', 30000, 30000, 8, 0, 0, 0, 0)
    frame = tmp_path / 'frame.png'
    frame.write_bytes(
        b'\x89PNG\r\n\x1a\n' + _chunk(b'IHDR', ihdr)
        + _chunk(b'IDAT', zlib.compress(b'\0' * 30001)) + _chunk(b'IEND', b'')
    )
    good = tmp_path / 'good.png'
    assert cv2.imwrite(str(good), np.full((20, 24), 90, np.uint8))

    def refuse(*args: object) -> None:
        raise AssertionError('cv2.imread was called: the image was decoded')

    monkeypatch.setattr(cv2, 'imread', refuse)
    out = tmp_path / 'mask.png'
    assert main([str(out), '--image', str(frame), '--below', '10']) == 2
    err = capsys.readouterr().err
    assert '--image' in err and 'declares more than' in err and 'Traceback' not in err
    assert not out.exists()
    monkeypatch.undo()
    assert main([str(out), '--image', str(good), '--below', '10']) == 0
