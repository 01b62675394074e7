"""The pipeline embedded in multi-threaded software: threads, kept results, cached state."""

from __future__ import annotations

import os
from pathlib import Path
import subprocess
import sys
import textwrap

import cv2
import numpy as np
import pytest

from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline


def _pair(seed: int, height: int = 32, width: int = 48) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    texture = rng.integers(0, 256, (height, width + 3), dtype=np.uint8)
    return np.ascontiguousarray(texture[:, 3:]), np.ascontiguousarray(texture[:, :width])


def _pipeline(**changes: object) -> StereoPipeline:
    config = PipelineConfig(matcher='census_bm', max_disparity=16, confidence_method='pkrn',
                            device='cpu')
    return StereoPipeline(config.replace(**changes))


def test_result_mask_cannot_be_edited_into_later_frames(tmp_path: Path) -> None:
    # Every result's mask was the pipeline's cached mask: an in-place edit of one result's
    # mask silently moved the rows processed of every later frame.
    mask = np.full((32, 48), 255, np.uint8)
    mask[28:, :10] = 0
    path = tmp_path / 'mask.png'
    cv2.imwrite(str(path), mask)
    pipeline = _pipeline(mask_path=str(path))
    first = pipeline.process(*_pair(0))
    assert first.mask is not None
    with pytest.raises(ValueError, match='read-only'):
        first.mask[:10] = False
    second = pipeline.process(*_pair(0))
    assert second.rows == first.rows == (0, 32)
    assert second.mask is not None and np.array_equal(second.mask, mask > 0)


def test_result_left_is_not_the_callers_buffer() -> None:
    # At downsample = 1 result.left was the caller's array: a driver that fills the same
    # buffer with the next frame changed the image of a result kept for later.
    pipeline = _pipeline()
    left, right = _pair(1)
    kept = left.copy()
    result = pipeline.process(left, right)
    left[:] = 0
    assert np.array_equal(result.left, kept)


_TWO_THREADS = textwrap.dedent("""
    import threading
    import numpy as np
    from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline

    def pair(seed):
        rng = np.random.default_rng(seed)
        texture = rng.integers(0, 256, (48, 99), dtype=np.uint8)
        return np.ascontiguousarray(texture[:, 3:]), np.ascontiguousarray(texture[:, :96])

    frames = [pair(seed) for seed in range(4)]
    pipelines = [
        StereoPipeline(PipelineConfig(matcher=matcher, max_disparity=depth,
                                      confidence_method='pkrn', device='cpu'))
        for matcher, depth in (('census_sgm', 16), ('census_bm', 32))
    ]
    expected = [[p.process(*f).confidence for f in frames] for p in pipelines]
    got = {}

    def work(index):
        got[index] = [pipelines[index].process(*f).confidence for f in frames * 10]

    threads = [threading.Thread(target=work, args=(i,)) for i in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for index in range(2):
        assert len(got[index]) == 40
        for n, values in enumerate(got[index]):
            assert np.array_equal(values, expected[index][n % 4], equal_nan=True)
    print('OK')
""")


def test_two_pipelines_in_two_threads_on_numbas_workqueue_layer() -> None:
    # numba's workqueue layer (no OpenMP/TBB library, or chosen by the environment) is not
    # thread-safe: two pipelines used from two threads terminated the whole process.
    env = dict(os.environ, NUMBA_THREADING_LAYER='workqueue')
    done = subprocess.run([sys.executable, '-c', _TWO_THREADS], env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().endswith('OK')
