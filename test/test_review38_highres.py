"""Review 38: high-resolution cameras and wide disparity ranges on small computers.

A frame whose matching cannot fit the memory left is refused up front with the need in GB and
what lowers it; numpy's lazy allocation of a 5 GB cost volume used to succeed and the kernel's
OOM killer then ended the process (a node) without a word. MC-CNN's feature network runs in
bands of rows: on the whole image its activations took 1.5 KB per pixel (3.1 GB at 1920×1080).
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

from cva_confidence_ros import memory
from cva_confidence_ros.errors import InputError
from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline


def _pipeline(**changes: object) -> StereoPipeline:
    values: dict[str, object] = {'confidence_method': 'pkrn', 'device': 'cpu'}
    values.update(changes)
    return StereoPipeline(PipelineConfig(**values))  # type: ignore[arg-type]


def _pair(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    texture = np.random.default_rng(0).integers(0, 256, (height, width + 4), dtype=np.uint8)
    return texture[:, 4:].copy(), texture[:, :width].copy()


def test_memory_needed_counts_volumes_and_sgm_work_arrays() -> None:
    width, height, depth = 2448, 2048, 512
    voxels = width * height * depth  # 2.6e9: past int32
    assert _pipeline(matcher='census_bm', max_disparity=depth).memory_needed(
        width, height) == 4 * voxels
    assert _pipeline(matcher='census_sgm', max_disparity=depth).memory_needed(
        width, height) == 7 * voxels
    assert _pipeline(matcher='census_bm', max_disparity=depth, lr_check=True).memory_needed(
        width, height) == 8 * voxels
    # Shrunk by the factor (crop to a multiple first), and only the rows processed.
    assert _pipeline(matcher='census_bm', max_disparity=64, downsample=2).memory_needed(
        2447, 2047) == 4 * 64 * 1223 * 1023
    roi = _pipeline(matcher='census_bm', max_disparity=64, roi_top=0.5)
    assert roi.memory_needed(640, 480) == 4 * 64 * 640 * (240 + 16)
    # MC-CNN: its 64 float32 features per pixel of both images on top of the volume.
    assert _pipeline(matcher='mccnn_fast', max_disparity=64).memory_needed(
        640, 480) == (4 * 64 + 2 * 64 * 4) * 640 * 480


def test_frame_beyond_memory_is_refused_with_need_and_knobs(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(memory, 'available_memory', lambda: int(7.5e9))
    sgm = _pipeline(matcher='census_sgm', max_disparity=256)
    with pytest.raises(InputError) as caught:
        sgm.check_input_size(2448, 2048)
    message = str(caught.value)
    assert '8.98 GB' in message and '7.50 GB' in message
    assert 'downsample = 2 (2.25 GB)' in message and 'max_disparity' in message
    assert memory.CHECK_SWITCH in message
    # What fits passes.
    sgm.check_input_size(1280, 720)
    _pipeline(matcher='census_sgm', max_disparity=256, downsample=2).check_input_size(2448, 2048)


def test_process_refuses_before_matching(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(memory, 'available_memory', lambda: 1000)
    monkeypatch.setattr(memory, '_CHECKED_FROM', 0)
    left, right = _pair(48, 64)
    with pytest.raises(InputError, match='needs at least'):
        _pipeline(matcher='census_bm', max_disparity=16).process(left, right)


def test_compute_cost_volume_refuses_volume_beyond_memory(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from cva_confidence_ros.matching import compute_cost_volume

    monkeypatch.setattr(memory, 'available_memory', lambda: 10_000)
    monkeypatch.setattr(memory, '_CHECKED_FROM', 0)
    left, right = _pair(48, 64)
    # 7 bytes per entry with SGM's work arrays: 7 × 16 × 48 × 64 = 344 064.
    with pytest.raises(InputError, match=r'census_sgm cost volume .* 0\.00 GB') as caught:
        compute_cost_volume(left, right, 'census_sgm', 16)
    assert 'max_disparity = 16' in str(caught.value)
    monkeypatch.setattr(memory, 'available_memory', lambda: 344_064)
    assert compute_cost_volume(left, right, 'census_sgm', 16).shape == (16, 48, 64)


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='reads /proc')
def test_available_memory(monkeypatch: pytest.MonkeyPatch) -> None:
    available = memory.available_memory()
    assert isinstance(available, int) and available > 0
    monkeypatch.setenv(memory.CHECK_SWITCH, '0')
    assert memory.available_memory() is None


def test_mccnn_features_in_bands_match_whole_image(monkeypatch: pytest.MonkeyPatch) -> None:
    import torch

    from cva_confidence_ros.matching import mccnn_net

    network = mccnn_net.load_network()
    left, right = _pair(37, 23)
    cpu = torch.device('cpu')
    monkeypatch.setattr(mccnn_net, 'BAND_BYTES', 1 << 40)
    whole = mccnn_net.extract_features(network, [left, right], cpu)
    seen: list[int] = []
    forward = network.forward

    def counting(images: torch.Tensor) -> torch.Tensor:
        seen.append(images.shape[2])
        return forward(images)

    # Bands of 5 rows (+ 10 of context), the last one shorter.
    monkeypatch.setattr(mccnn_net, 'BAND_BYTES', 2 * 64 * 4 * 4 * 23 * 5)
    monkeypatch.setattr(network, 'forward', counting)
    banded = mccnn_net.extract_features(network, [left, right], cpu)
    assert seen == [15] * 7 + [12]
    torch.testing.assert_close(banded, whole, rtol=0, atol=1e-5)
    # Each image's (H, W, 64) as the correlation reads it, without a copy.
    assert banded[0].permute(1, 2, 0).is_contiguous()



def test_mccnn_features_on_a_gpu_are_not_counted_as_host_memory(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # On a GPU the 2·64 float32 features per pixel live there: counted as host memory they
    # overstated a 2448×2048 frame's need by 2.6 GB (a desktop with a GPU refused it).
    import torch

    from cva_confidence_ros import matching
    from cva_confidence_ros.errors import CVAError

    pipe = _pipeline(matcher='mccnn_fast', max_disparity=64)
    monkeypatch.setattr(pipe, 'device', torch.device('cuda'))
    assert pipe.memory_needed(640, 480) == 4 * 64 * 640 * 480
    monkeypatch.setattr(memory, '_CHECKED_FROM', 0)
    monkeypatch.setattr(memory, 'available_memory', lambda: int(0.3e9))
    left, right = _pair(1200, 800)
    # The volume 4·64·1200·800 = 0.25 GB, the features 0.49 GB more on the CPU.
    with pytest.raises(InputError, match=r'needs at least 0\.74 GB'):
        matching.compute_cost_volume(left, right, 'mccnn_fast', 64, device='cpu')
    monkeypatch.setattr(matching, '_cuda_available', lambda: True)
    # On 'cuda' the memory check passes (0.25 GB); what stops it here is the missing GPU.
    with pytest.raises(CVAError) as caught:
        matching.compute_cost_volume(left, right, 'mccnn_fast', 64, device='cuda')
    assert 'GB' not in str(caught.value)


def test_a_memory_refusal_is_its_own_input_error(monkeypatch: pytest.MonkeyPatch) -> None:
    # The node tells a step toward a configuration that fits from other refusals by the
    # class (it read the traceback's last frame name), and callers may catch it alone.
    from cva_confidence_ros.errors import MemoryShortfallError
    from cva_confidence_ros.matching import compute_cost_volume

    monkeypatch.setattr(memory, 'available_memory', lambda: 10_000)
    monkeypatch.setattr(memory, '_CHECKED_FROM', 0)
    with pytest.raises(MemoryShortfallError):
        _pipeline(matcher='census_bm', max_disparity=16).check_input_size(64, 48)
    left, right = _pair(48, 64)
    with pytest.raises(MemoryShortfallError, match='cva-evaluate --downsample'):
        compute_cost_volume(left, right, 'census_bm', 16)
    assert issubclass(MemoryShortfallError, InputError)


def test_a_refusal_with_no_downsample_alone_names_one_with_a_smaller_depth(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # 2448×2048 with census_sgm at D = 256 and 0.5 GB left: neither downsample 2 (2.25 GB)
    # nor 4 (0.56 GB) fits alone; the message offered only "a smaller max_disparity".
    monkeypatch.setattr(memory, 'available_memory', lambda: int(0.5e9))
    sgm = _pipeline(matcher='census_sgm', max_disparity=256)
    with pytest.raises(InputError) as caught:
        sgm.check_input_size(2448, 2048)
    message = str(caught.value)
    assert 'downsample = 4 with max_disparity = 64 (the same depth range, 0.14 GB)' in message
    assert 'a smaller max_disparity (now 256; 8: 0.28 GB)' in message
    taken = _pipeline(matcher='census_sgm', max_disparity=64, downsample=4)
    taken.check_input_size(2448, 2048)  # what it names fits
