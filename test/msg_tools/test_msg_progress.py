"""Progress lines, Ctrl-C deferral inside critical sections, and the live node's arguments."""

from __future__ import annotations

import io
import os
from pathlib import Path
import signal

import pytest

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
        with pytest.raises(KeyboardInterrupt):
            with interrupts.critical():
                os.kill(os.getpid(), signal.SIGINT)
                steps.append('finished the section')
        assert steps == ['finished the section'] and interrupts.requested
        interrupts.closing()
        os.kill(os.getpid(), signal.SIGTERM)  # only noted while the outputs are closed
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
