"""Review 32 of the live replay (``msg_tools.live``): frames that share a stamp, a node that
exits, outputs that cannot be read, the node's string parameters, a node that answers nothing.
Driven without DDS: the recorder directly, or the play loop with a stand-in player whose
publishers hand each pair to the node's own code."""

from __future__ import annotations

import copy
import gc
import io
from pathlib import Path
import queue
import time
from types import SimpleNamespace
from typing import Any, cast
import weakref

from msg_test_utils import START_NS, live_options, read_bag, write_stereo_bag
import pytest

from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline
from msg_tools import live
from msg_tools.bagio import InputBag
from msg_tools.convert import jazzy_typestore, stamp_to_ns
from msg_tools.progress import GracefulInterrupt, Progress
from msg_tools.replay import (
    ReplayOptions,
    ReplayOutcome,
    ReplaySession,
    TopicPlan,
    make_synchronizer,
    node_outputs,
    plan_topics,
    stereo_inputs,
)

MS = 1_000_000
SCORED = ('disparity', 'confidence', 'disparity_filtered')


def _pairs(options: ReplayOptions) -> tuple[TopicPlan, list[tuple[int, dict[str, Any], int]]]:
    """The bag's plan and its pairs in bag order: (stamp, inputs by key, bag time)."""
    store = jazzy_typestore()
    pairs: list[tuple[int, dict[str, Any], int]] = []
    with InputBag(options.bag) as source:
        plan = plan_topics(source, options, lambda _: None)
        items: dict[str, Any] = {}
        for topic, kind, timestamp, raw in source.messages(list(plan.inputs.values())):
            msg = store.deserialize_cdr(raw, kind)
            items[plan.key_of[topic]] = msg
            if len(items) == 4:
                pairs.append((stamp_to_ns(msg.header.stamp), items, timestamp))
                items = {}
    return plan, pairs


def _answer(options: ReplayOptions, items: dict[str, Any]) -> list[tuple[str, str, bytes]]:
    """What the node publishes for a pair, in its order."""
    left, right, geometry = stereo_inputs(items)
    return node_outputs(
        StereoPipeline(options.pipeline).process(left, right), geometry, left.shape[:2],
        items['left'].header, options.pipeline, left_info=items['left_info'],
    ).messages


def _progress() -> Progress:
    return Progress(1, stream=io.StringIO())


def test_frames_of_one_stamp_waited_for_together_are_each_answered(tmp_path: Path) -> None:
    # A looped bag of two frames, the loop shorter than the node's latency: frames 0 and 2
    # (stamp A) and 1 and 3 (stamp B) all wait at once. They shared one slot per stamp: frame
    # 2 took frame 0's, frame 0's outputs were scored as frame 2's and written at its bag
    # time, and frames 2 and 3 were counted dropped although answered (2 of 4 answered).
    frames = [dict(stamp=START_NS + i * 100 * MS, logged=START_NS + k * 100 * MS)
              for k, i in enumerate([0, 1, 0, 1])]
    options = live_options(tmp_path, write_stereo_bag(tmp_path / 'in', frames, ground_truth=False))
    plan, pairs = _pairs(options)
    session = ReplaySession(options, plan, lambda _: None)
    recorder = live._Recorder(session, jazzy_typestore(), options, queue.Queue())
    answers = [_answer(options, pairs[index][1]) for index in (0, 1)] * 2  # the loop's data
    scored = [[m for m in answer if m[0] in SCORED] for answer in answers]
    late = [[m for m in answer if m[0] not in SCORED] for answer in answers]
    with session:
        for index, (stamp, items, logged) in enumerate(pairs):
            recorder.expect(SimpleNamespace(stamp_ns=stamp, items=items), index, logged)
            session.counts['pairs'] += 1
        # In the node's order on each topic; a frame's points2, depth and camera_info come
        # two frames late.
        for batch in (scored[0], scored[1], scored[2], late[0], scored[3], late[1], late[2],
                      late[3]):
            for name, _, raw in batch:
                recorder._handle(name, raw, time.monotonic(), _progress())
    assert (recorder.answered, recorder.unanswered()) == (4, 0)
    assert [score.frame for score in session.report.frames] == [0, 1, 2, 3]
    written = read_bag(tmp_path / 'out')
    assert len(written) == 6
    for topic, entries in written.items():
        assert [t - START_NS for t, _ in entries] == [0, 100 * MS, 200 * MS, 300 * MS], topic


class _Publisher:
    def __init__(self, player: _Player, topic: str) -> None:
        self.player, self.topic = player, topic

    def publish(self, raw: bytes) -> None:
        self.player.take(self.topic, raw)


class _Player:
    """The player without DDS: the node's synchroniser and pipeline answer each pair at once;
    ``answered(index)`` is called after a pair's outputs are queued."""

    def __init__(self, plan: TopicPlan, options: ReplayOptions, answered: Any) -> None:
        self.plan, self.options, self.answered = plan, options, answered
        self.store = jazzy_typestore()
        self.sync = make_synchronizer(options)
        self.received: queue.Queue[tuple[str, bytes, float]] = queue.Queue()
        self.publishers = {topic: _Publisher(self, topic) for topic in plan.input_types}
        self.pairs = 0

    def take(self, topic: str, raw: bytes) -> None:
        msg = self.store.deserialize_cdr(raw, self.plan.input_types[topic])
        for matched in self.sync.add(self.plan.key_of[topic], stamp_to_ns(msg.header.stamp),
                                     msg):
            for name, _, data in _answer(self.options, matched.items):
                self.received.put((name, data, time.monotonic()))
            self.pairs += 1
            self.answered(self.pairs - 1)


class _Node:
    """A started node that exits at ``died`` (monotonic seconds)."""

    died = float('inf')

    @property
    def exit_code(self) -> int | None:
        return 1 if time.monotonic() >= self.died else None

    def last_lines(self) -> str:
        return 'Segmentation fault'


def _play(tmp_path: Path, bag: Path, node: _Node, answered: Any) -> tuple[ReplayOutcome, int]:
    options = live_options(tmp_path, bag)
    _answer(options, _pairs(options)[1][0][1])  # compiles the matcher before the clock runs
    with InputBag(bag) as source:
        plan = plan_topics(source, options, lambda _: None)
        player = _Player(plan, options, answered)
        outcome = live._play(source, plan, cast(Any, player), cast(Any, node), options,
                             lambda _: None, GracefulInterrupt())
    return outcome, player.pairs


def test_outputs_received_before_the_node_exits_are_recorded(tmp_path: Path) -> None:
    # The node answers pairs 0 and 1 and dies: pair 1's outputs had come, but the replay
    # stopped on the exit before it handled them: 1 processed, 1 dropped, 1 in the bag.
    node = _Node()

    def answered(index: int) -> None:
        if index == 1:
            node.died = time.monotonic()

    outcome, answers = _play(tmp_path, write_stereo_bag(tmp_path / 'in', [{}] * 4,
                                                        ground_truth=False), node, answered)
    assert outcome.exit_code == 2
    assert 'cva-node exited with code 1: Segmentation fault' in outcome.message
    counts = outcome.report.counts
    assert answers == 2
    assert (counts['pairs'], counts['processed'], counts['dropped']) == (2, 2, 0)
    assert len(read_bag(tmp_path / 'out')['/disparity']) == 2


def test_a_node_that_exits_during_a_pause_of_the_bag_ends_the_replay_at_once(
    tmp_path: Path,
) -> None:
    # 4 s between the bag's two frames; the node dies 0.1 s after the first. The replay
    # looked at the node only before each message: it waited out the pause (3.9 s more).
    node = _Node()

    def answered(index: int) -> None:
        node.died = time.monotonic() + 0.1

    bag = write_stereo_bag(tmp_path / 'in', [{}, {'stamp': START_NS + 4000 * MS}],
                           ground_truth=False)
    outcome, answers = _play(tmp_path, bag, node, answered)
    assert time.monotonic() - node.died < 2.0
    assert outcome.exit_code == 2 and 'cva-node exited with code 1' in outcome.message
    assert answers == 1 and outcome.report.counts['processed'] == 1


def _answer_cut(
    tmp_path: Path, cut: tuple[str, ...] | None, log: Any
) -> tuple[ReplaySession, Any]:
    """Two pairs answered through the recorder, the outputs named in ``cut`` (None: all)
    cut short to 12 bytes."""
    options = live_options(tmp_path, write_stereo_bag(tmp_path / 'in', [{}, {}],
                                                  ground_truth=False))
    plan, pairs = _pairs(options)
    session = ReplaySession(options, plan, log)
    recorder = live._Recorder(session, jazzy_typestore(), options, queue.Queue())
    with session:
        for index, (stamp, items, logged) in enumerate(pairs):
            recorder.expect(SimpleNamespace(stamp_ns=stamp, items=items), index, logged)
            session.counts['pairs'] += 1
            for name, _, raw in _answer(options, items):
                short = cut is None or name in cut
                recorder._handle(name, raw[:12] if short else raw, time.monotonic(),
                                 _progress())
    return session, recorder


def test_an_output_that_cannot_be_read_is_no_skipped_pair(tmp_path: Path) -> None:
    # A points2 cut short: counted as a skipped pair besides its frame, processed (1 pair,
    # 1 processed + 1 skipped), and logged once per message.
    logs: list[str] = []
    session, recorder = _answer_cut(tmp_path, ('points',), logs.append)
    counts = session.counts
    assert (counts['pairs'], counts['processed'], counts['skipped']) == (2, 2, 0)
    assert counts['unreadable'] == 2 and recorder.unanswered() == 0
    unreadable = [line for line in logs if '/points2' in line]
    assert len(unreadable) == 1 and unreadable[0].startswith('skipped an output on /points2')


def test_string_parameters_reach_the_node_as_they_are(tmp_path: Path) -> None:
    # rcl reads a -p value as YAML: a mask in 'run #2/' reached the node as '.../run' (the
    # rest a comment) and a model file named '123' as an integer.
    rclpy = pytest.importorskip('rclpy')
    from rclpy.context import Context
    from rclpy.signals import SignalHandlerOptions

    mask = str(tmp_path / 'run #2' / 'mask.png')
    options = ReplayOptions(
        bag=tmp_path / 'in', out=tmp_path / 'out', report=tmp_path / 'report', mode='live',
        pipeline=PipelineConfig(matcher='census_bm', confidence_method='pkrn',
                                mask_path=mask, model_path='123'),
    )
    args = live.node_arguments(options, 'replayed')
    params = {args[i + 1] for i, a in enumerate(args) if a == '-p'}
    assert {'matcher:=census_bm', 'input_qos:=reliable'} <= params  # plain names stay plain
    context = Context()
    rclpy.init(context=context, args=args, signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = rclpy.create_node('review32_params', context=context,
                                 automatically_declare_parameters_from_overrides=True)
        values = {name: node.get_parameter(name).value
                  for name in ('mask_path', 'model_path', 'matcher', 'depth_encoding')}
        node.destroy_node()
    finally:
        context.try_shutdown()
    assert values == {'mask_path': mask, 'model_path': '123', 'matcher': 'census_bm',
                      'depth_encoding': '32FC1'}
    assert live._ros_value("it's") == "'it''s'"
    assert live._ros_value('true') == "'true'" and live._ros_value('nan') == "'nan'"


def test_a_node_that_answers_nothing_does_not_have_every_image_held(tmp_path: Path) -> None:
    # Each frame waited for kept its input messages: a silent node had the replay hold every
    # image of the bag (a 5-minute 10 Hz VGA bag: 1.8 GB). Only the newest hundred do now.
    options = live_options(tmp_path, write_stereo_bag(tmp_path / 'in', [{}], ground_truth=False))
    plan, [(_, items, _)] = _pairs(options)
    recorder = live._Recorder(
        ReplaySession(options, plan, lambda _: None), jazzy_typestore(), options, queue.Queue()
    )
    lefts = []
    for frame in range(300):
        left = copy.copy(items['left'])
        lefts.append(weakref.ref(left))
        recorder.expect(SimpleNamespace(stamp_ns=START_NS + frame, items={**items, 'left': left}),
                        frame, frame)
        del left
    gc.collect()
    assert [ref() is not None for ref in lefts] == [False] * 200 + [True] * 100
    assert sum(map(len, recorder.frames.values())) == 300  # all still waited for


def test_a_replay_whose_every_output_was_unreadable_says_so(tmp_path: Path) -> None:
    # Every output cut short: the closing line said only that the node answered none of the
    # pairs, though it did, unreadably.
    session, _ = _answer_cut(tmp_path, None, lambda _: None)
    outcome = session.outcome()
    assert session.counts['processed'] == 0 and session.counts['unreadable'] > 0
    assert outcome.exit_code == 2
    assert 'the node answered none of the 2 stereo pairs; ' in outcome.message
    assert f"{session.counts['unreadable']} messages could not be read" in outcome.message
