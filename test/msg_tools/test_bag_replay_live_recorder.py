"""Live mode's recorder without DDS: the node's outputs, made by the node's own code from a real
bag, handed to it in the node's publish order; what it writes into the output bag and scores."""

from __future__ import annotations

import io
from pathlib import Path
import queue
from types import SimpleNamespace
from typing import Any

from msg_test_utils import START_NS, read_bag, textured_pair, write_stereo_bag
import pytest

from cva_confidence_ros.pipeline import StereoPipeline
from cva_confidence_ros.pointcloud import StereoGeometry
from msg_tools.bag_replay import build_parser, options_from_args
from msg_tools.bagio import InputBag
from msg_tools.convert import jazzy_typestore, stamp_to_ns
from msg_tools.live import _Recorder
from msg_tools.progress import Progress
from msg_tools.replay import (
    FrameResult,
    ReplaySession,
    node_outputs,
    plan_topics,
    stereo_inputs,
)

# A robot's bag: each input logged when it was received, well after its header stamp.
RECEIVED_AFTER_NS = 3_000_000_000


def _answers(
    tmp_path: Path, frames: list[dict[str, Any]], *extra: str
) -> tuple[ReplaySession, _Recorder, list[tuple[int, list[tuple[str, str, bytes]]]]]:
    """A live session with its recorder, every frame of a hand-made bag registered as
    published (at bag time stamp + :data:`RECEIVED_AFTER_NS`), and per frame its stamp and the
    messages the node publishes for it, in the node's order."""
    bag = write_stereo_bag(tmp_path / 'in', frames)
    options = options_from_args(build_parser().parse_args([
        str(bag), '--mode', 'live', '--out', str(tmp_path / 'out'),
        '--report', str(tmp_path / 'report'), '--matcher', 'census_bm',
        '--confidence-method', 'pkrn', '--device', 'cpu', *extra,
    ]))
    store = jazzy_typestore()
    with InputBag(bag) as source:
        plan = plan_topics(source, options, lambda _: None)
        by_stamp: dict[int, dict[str, Any]] = {}
        for topic, msgtype, _, raw in source.messages(list(plan.inputs.values())):
            msg = store.deserialize_cdr(raw, msgtype)
            by_stamp.setdefault(stamp_to_ns(msg.header.stamp), {})[plan.key_of[topic]] = msg
    session = ReplaySession(options, plan, lambda _: None, truth_window=50)
    recorder = _Recorder(session, store, options, queue.Queue())
    pipeline = StereoPipeline(options.pipeline)
    answers = []
    for frame, (stamp, items) in enumerate(sorted(by_stamp.items())):
        matched = SimpleNamespace(stamp_ns=stamp, items=items)
        recorder.expect(matched, frame, stamp + RECEIVED_AFTER_NS)
        left, right, geometry = stereo_inputs(items)
        outputs = node_outputs(
            pipeline.process(left, right), geometry, left.shape[:2], items['left'].header,
            options.pipeline, left_info=items['left_info'],
        )
        answers.append((stamp, outputs.messages))
    session.counts['pairs'] = len(answers)
    return session, recorder, answers


def _progress() -> Progress:
    return Progress(1, stream=io.StringIO())


def test_late_outputs_of_a_frame_are_written_at_its_bag_time(tmp_path: Path) -> None:
    session, recorder, answers = _answers(tmp_path, [{}, {}], '--max-disparity', '16')
    scored = ('disparity', 'confidence', 'disparity_filtered')
    with session:
        # Both frames complete first; the points, depth and camera info of the first come
        # after the second frame is done, as they may over DDS.
        for only_scored in (True, False):
            for _, messages in answers:
                for name, _, raw in messages:
                    if (name in scored) == only_scored:
                        recorder._handle(name, raw, 1.0, _progress())
    written = read_bag(tmp_path / 'out')
    assert set(written) == {'/disparity', '/confidence', '/disparity_filtered', '/points2',
                            '/depth', '/camera_info'}
    for topic, entries in written.items():
        assert len(entries) == 2, topic
        for timestamp, msg in entries:
            assert timestamp == stamp_to_ns(msg.header.stamp) + RECEIVED_AFTER_NS, topic
    assert answers[0][0] == START_NS and recorder.answered == 2


def test_odd_size_with_downsample_is_scored_with_the_node_geometry(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # 41×31 px at downsample 2: the node crops to 40×30 and halves exactly.
    frames = [dict(zip(('left', 'right'), textured_pair(31, 41, 4, 0), strict=True))]
    session, recorder, answers = _answers(
        tmp_path, frames, '--downsample', '2', '--max-disparity', '8'
    )
    results: list[FrameResult] = []
    add_result = session.add_result
    monkeypatch.setattr(session, 'add_result', lambda r: (results.append(r), add_result(r)))
    with session:
        for name, _, raw in answers[0][1]:
            recorder._handle(name, raw, 1.0, _progress())
    node = StereoGeometry(fx=50.0, fy=50.0, cx=20.0, cy=15.0, cx_right=20.0,
                          baseline=0.1).scaled(0.5)
    [result] = results
    assert result.geometry is not None
    assert result.geometry.fx == result.geometry.fy == 25.0
    assert (result.geometry.cx, result.geometry.cy) == pytest.approx((node.cx, node.cy))
    [(_, info)] = read_bag(tmp_path / 'out')['/camera_info']
    assert info.p[0] == result.geometry.fx
