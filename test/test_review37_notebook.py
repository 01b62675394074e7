"""Review 37: the Python API as a notebook user drives it (reprs, threads, own ground truth)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import warnings

import numpy as np
import pytest

from cva_confidence_ros.confidence import ConfidenceInputs
from cva_confidence_ros.metrics import evaluate_confidence
from cva_confidence_ros.pipeline import PipelineConfig, PipelineResult, StereoPipeline


def _pair(height: int = 24, width: int = 40, shift: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Random texture at disparity ``shift``: left (x) is right (x − shift)."""
    texture = np.random.default_rng(1).integers(0, 256, (height, width + shift), dtype=np.uint8)
    return texture[:, :width].copy(), texture[:, shift:].copy()


def _torch_threads_after(lines: str) -> str:
    """The stdout of a fresh process (numba starts its OpenMP threads once per process) that
    sets torch to 1 thread, runs ``lines`` on a 24×40 pair (``left``, ``right``) and prints
    torch's thread count."""
    script = textwrap.dedent("""
        import numpy as np
        import torch
        torch.set_num_threads(1)
        assert torch.get_num_threads() == 1
        texture = np.random.default_rng(0).integers(0, 256, (24, 43), dtype=np.uint8)
        left, right = texture[:, :40].copy(), texture[:, 3:].copy()
    """) + textwrap.dedent(lines) + "print('threads', torch.get_num_threads())\n"
    done = subprocess.run([sys.executable, '-c', script], capture_output=True, text=True,
                          timeout=300, check=False)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_torch_thread_count_set_by_the_user_survives_the_first_frame() -> None:
    # numba starts its OpenMP threads on the first frame. It set OpenMP's count (shared with
    # torch) to its own, and torch.set_num_threads(1) read 2.
    assert 'threads 1' in _torch_threads_after("""
        from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline
        pipeline = StereoPipeline(PipelineConfig(max_disparity=8, confidence_method='pkrn',
                                                 device='cpu'))
        pipeline.process(left, right)
    """)


def test_torch_thread_count_survives_a_cost_volume_computed_directly() -> None:
    # compute_cost_volume outside a pipeline (MC-CNN's parallel correlation) started numba's
    # OpenMP threads unguarded: torch.set_num_threads(1) read 2 after it.
    assert 'threads 1' in _torch_threads_after("""
        from cva_confidence_ros.matching import compute_cost_volume
        compute_cost_volume(left, right, 'mccnn_fast', 8)
    """)


def test_result_and_pipeline_reprs_are_one_line() -> None:
    pipeline = StereoPipeline(PipelineConfig(max_disparity=8, confidence_method='pkrn',
                                             device='cpu', roi_top=0.25, speckle_size=0))
    text = repr(pipeline)
    assert '\n' not in text
    assert "confidence_method='pkrn'" in text and 'roi_top=0.25' in text
    assert 'speckle_size=0' in text and 'running on cpu' in text
    assert 'model_path' not in text  # a default
    result = pipeline.process(*_pair())
    text = repr(result)
    # The dataclass's repr printed the six maps: dozens of lines of numbers.
    assert '\n' not in text and len(text) < 200, text
    assert text.startswith('PipelineResult(40×24 px')
    assert 'rows=(6, 24)' in text and 'kept_fraction=' in text
    assert isinstance(result, PipelineResult)


def test_confidence_inputs_repr_is_one_line() -> None:
    volume = np.random.default_rng(2).random((16, 20, 30), dtype=np.float32)
    inputs = ConfidenceInputs(volume, volume.argmin(0).astype(np.float32),
                              np.zeros((20, 30), np.uint8), matcher='census_bm')
    text = repr(inputs)
    assert '\n' not in text and len(text) < 200, text
    assert 'D=16' in text and '30×20 px' in text and "'census_bm'" in text


def test_evaluate_confidence_warns_about_ground_truth_of_zero() -> None:
    # KITTI-style ground truth: 0 = no measurement. Taken as disparity 0 it counted every
    # empty pixel, silently (error rate 0.74 instead of 0.17 on a 30 % dense map).
    rng = np.random.default_rng(0)
    truth = rng.uniform(5, 60, (30, 40))
    estimate = truth + rng.normal(0, 0.5, truth.shape)
    confidence = rng.random(truth.shape)
    d_gt = np.where(rng.random(truth.shape) < 0.3, truth, 0.0)
    with pytest.warns(RuntimeWarning, match=r'd_gt is exactly 0 at \d+ of the 1200'):
        evaluate_confidence(confidence, estimate, d_gt)
    with warnings.catch_warnings():
        warnings.simplefilter('error')
        scores = evaluate_confidence(confidence, estimate, np.where(d_gt > 0, d_gt, np.nan))
    assert scores['error_rate'] == 0.0 and scores['n_pixels'] == np.count_nonzero(d_gt)


def test_warm_up_pair_has_a_positive_disparity(monkeypatch: pytest.MonkeyPatch) -> None:
    # The warm-up pair was at disparity −2: nothing matched, nothing confident, nothing kept.
    pipeline = StereoPipeline(PipelineConfig(max_disparity=8, confidence_method='pkrn',
                                             device='cpu', confidence_threshold=0.1))
    seen: list[PipelineResult] = []
    run = pipeline._run

    def spy(*args: object) -> PipelineResult:
        seen.append(run(*args))  # type: ignore[arg-type]
        return seen[-1]

    monkeypatch.setattr(pipeline, '_run', spy)
    pipeline.warm_up()
    assert float(np.nanmedian(seen[0].disparity)) == pytest.approx(2.0, abs=0.5)
    assert seen[0].kept_fraction > 0.5
