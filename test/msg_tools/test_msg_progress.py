"""Progress lines, Ctrl-C deferral inside critical sections, and the live node's arguments."""

from __future__ import annotations

import io
import os
from pathlib import Path
import signal
import threading
import time

import numpy as np
import pytest

from cva_confidence_ros.confidence.handcrafted import two_smallest
from cva_confidence_ros.pipeline import PipelineConfig
from msg_tools.live import node_arguments
from msg_tools.progress import GracefulInterrupt, Progress
from msg_tools.replay import ReplayOptions, TopicNames


def test_progress_reports_rate_and_time_left() -> None:
    now = [0.0]
    stream = io.StringIO()
    progress = Progress(10, prefix='p: ', stream=stream, interval=1.0, clock=lambda: now[0])
    now[0] = 2.0
    progress.update()  # 1 frame in 2 s: 0.5 fps, 9 frames left = 18 s
    now[0] = 2.5
    progress.update()  # within the interval: not printed
    now[0] = 4.0
    progress.update()
    progress.finish()  # the last line said 3/10 already
    assert stream.getvalue().splitlines() == [
        'p: 1/10 frames, 0.50 fps, ~18 s left',
        'p: 3/10 frames, 0.75 fps, ~9 s left',
    ]


def test_signal_waits_for_the_critical_section() -> None:
    # CI may start the suite with SIGINT ignored (a background job): restore what was there.
    original = signal.getsignal(signal.SIGINT)
    steps = []
    with GracefulInterrupt() as interrupts:
        with interrupts.critical():
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)  # not even a second one cuts it short
            time.sleep(0.05)
            steps.append('finished the section')
        assert steps == ['finished the section'] and interrupts.requested
        with pytest.raises(KeyboardInterrupt):
            interrupts.check()
        interrupts.closing()
        os.kill(os.getpid(), signal.SIGTERM)  # only noted while the outputs are closed
    assert signal.getsignal(signal.SIGINT) is original


def _signal_soon(sig: int = signal.SIGINT, delay: float = 0.05) -> threading.Timer:
    timer = threading.Timer(delay, os.kill, (os.getpid(), sig))
    timer.start()
    return timer


def test_a_first_signal_is_noted_and_raised_at_the_next_check(
    capsys: pytest.CaptureFixture[str],
) -> None:
    original = signal.getsignal(signal.SIGINT)
    with GracefulInterrupt(notice='stopping after this frame') as interrupts:
        # A numba kernel that takes a while, with the signal arriving half-way: numba calls back
        # into Python to hand the result arrays over, and an exception raised there by Python's
        # own handler came out as "SystemError: CPUDispatcher(...) returned a result with an
        # exception set" (cva-bag-replay then exited 1 with a traceback instead of 130).
        volume = np.random.default_rng(0).random((600, 800, 64), dtype=np.float32)
        two_smallest(volume[:8, :8])  # compiled before the clock starts
        timer = _signal_soon()
        while not interrupts.requested:
            c1, _, c2 = two_smallest(volume)
        timer.join()
        assert (c1 <= c2).all()  # the kernel's result, whole
        with pytest.raises(KeyboardInterrupt):
            interrupts.check()
    assert 'stopping after this frame (Ctrl-C again to stop at once)' in capsys.readouterr().err
    assert signal.getsignal(signal.SIGINT) is original


def test_a_second_signal_is_raised_at_once() -> None:
    with GracefulInterrupt() as interrupts:
        os.kill(os.getpid(), signal.SIGINT)
        assert interrupts.requested
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)  # a long step: the second signal does not wait for it
        # Once the outputs are being closed, signals are only noted.
        interrupts.closing()
        os.kill(os.getpid(), signal.SIGINT)
        interrupts.check()


def test_entered_again_the_handlers_stay_until_the_outermost_exit() -> None:
    original = signal.getsignal(signal.SIGINT)
    interrupts = GracefulInterrupt()
    with interrupts:
        with interrupts:
            pass
        assert signal.getsignal(signal.SIGINT) == interrupts._handler
        os.kill(os.getpid(), signal.SIGINT)
        with pytest.raises(KeyboardInterrupt):
            interrupts.check()
    assert signal.getsignal(signal.SIGINT) is original


def test_node_arguments_mirror_the_replay_options(tmp_path: Path) -> None:
    options = ReplayOptions(
        bag=tmp_path / 'in', out=tmp_path / 'out', report=tmp_path / 'report',
        pipeline=PipelineConfig(matcher='census_sgm', max_disparity=32, confidence_method='pkrn',
                                downsample=2, confidence_threshold=0.25),
        topics=TopicNames(prefix='/stereo', left='/cam0/image'),
        approximate_sync=True, sync_tolerance_s=0.004, queue_size=7, publish_points=False,
    )
    args = node_arguments(options, 'replayed')
    assert args[:3] == ['--ros-args', '-r', '__node:=replayed']
    params = {args[i + 1] for i, a in enumerate(args) if a == '-p'}
    remaps = {args[i + 1] for i, a in enumerate(args) if a == '-r'}
    assert {'matcher:=census_sgm', 'max_disparity:=32', 'confidence_method:=pkrn',
            'downsample:=2', 'confidence_threshold:=0.25', 'lr_check:=false',
            'tile_budget_mb:=512.0', 'approximate_sync:=true',
            'approximate_sync_tolerance_seconds:=0.004', 'queue_size:=7',
            'publish_points:=false', 'input_qos:=reliable', 'output_qos:=reliable'} <= params
    assert not any(p.startswith('model_path') for p in params)  # '' is the node's default
    assert {'left/image_rect:=/cam0/image', 'right/image_rect:=/stereo/right/image_rect',
            'left/camera_info:=/stereo/left/camera_info', 'disparity:=/stereo/disparity',
            'points2:=/stereo/points2'} <= remaps
    assert 'image_transport:=raw' in params
    # A bag of image_transport compressed images: the node takes them on .../compressed.
    args = node_arguments(options, 'replayed', 'compressed')
    params = {args[i + 1] for i, a in enumerate(args) if a == '-p'}
    remaps = {args[i + 1] for i, a in enumerate(args) if a == '-r'}
    assert 'image_transport:=compressed' in params
    assert {'left/image_rect/compressed:=/cam0/image',
            'right/image_rect/compressed:=/stereo/right/image_rect',
            'left/camera_info:=/stereo/left/camera_info'} <= remaps
