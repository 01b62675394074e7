"""Review 31 of the live replay (``msg_tools.live``): its play loop driven without DDS, by a
stand-in for the player whose publishers hand each pair to the node's own code and queue what
the node would publish, as the real player's subscriptions do."""

from __future__ import annotations

import io
import os
from pathlib import Path
import queue
import signal
import time
from types import SimpleNamespace
from typing import Any, cast

from msg_test_utils import START_NS, live_options, read_bag, write_stereo_bag
import pytest

from cva_confidence_ros.pipeline import StereoPipeline
from msg_tools import live
from msg_tools.bagio import InputBag, OutputBag
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


class _Publisher:
    def __init__(self, player: _Player, topic: str) -> None:
        self.player, self.topic = player, topic

    def publish(self, raw: bytes) -> None:
        self.player.take(self.topic, raw)


class _Player:
    """The player without DDS: the node's synchroniser and pipeline answer each pair at once
    (pairs whose index is in ``silent`` get no answer); ``answered(player, index)`` is called
    after a pair's outputs are queued."""

    def __init__(
        self, plan: TopicPlan, options: ReplayOptions, silent: set[int] | None = None,
        answered: Any = None,
    ) -> None:
        self.plan, self.options = plan, options
        self.silent = silent or set()
        self.answered = answered
        self.store = jazzy_typestore()
        self.sync = make_synchronizer(options)
        self.pipeline = StereoPipeline(options.pipeline)
        self.received: queue.Queue[tuple[str, bytes, float]] = queue.Queue()
        self.publishers = {topic: _Publisher(self, topic) for topic in plan.input_types}
        self.sent = 0  # input messages published
        self.pairs = 0

    def take(self, topic: str, raw: bytes) -> None:
        self.sent += 1
        msg = self.store.deserialize_cdr(raw, self.plan.input_types[topic])
        for matched in self.sync.add(self.plan.key_of[topic], stamp_to_ns(msg.header.stamp),
                                     msg):
            index, self.pairs = self.pairs, self.pairs + 1
            if index in self.silent:
                continue
            left, right, geometry = stereo_inputs(matched.items)
            outputs = node_outputs(
                self.pipeline.process(left, right), geometry, left.shape[:2],
                matched.items['left'].header, self.options.pipeline,
                left_info=matched.items['left_info'],
            )
            for name, _, data in outputs.messages:
                self.received.put((name, data, time.monotonic()))
            if self.answered is not None:
                self.answered(self, index)


def _play(
    tmp_path: Path, bag: Path, *extra: str, node: Any = None, **player: Any
) -> tuple[ReplayOutcome, _Player]:
    options = live_options(tmp_path, bag, *extra)
    with InputBag(bag) as source:
        plan = plan_topics(source, options, lambda _: None)
        fake = _Player(plan, options, **player)
        warm = write_stereo_bag(tmp_path / 'warm', [{}], ground_truth=False)
        with InputBag(warm) as other:  # compiles the matcher before the clock runs
            store = jazzy_typestore()
            items = {plan.key_of[t]: store.deserialize_cdr(raw, kind)
                     for t, kind, _, raw in other.messages(list(plan.inputs.values()))}
        fake.pipeline.process(*stereo_inputs(items)[:2])
        outcome = live._play(source, plan, cast(Any, fake), node, options, lambda _: None,
                             GracefulInterrupt())
    return outcome, fake


def _relogged(source: Path, path: Path, after_ms: dict[str, int]) -> Path:
    """``source`` with the messages of each topic logged ``after_ms`` later."""
    from rosbags.rosbag2 import Reader

    store = jazzy_typestore()
    with Reader(source) as reader, OutputBag(path, 'mcap', store) as out:
        for conn, timestamp, data in reader.messages():
            out.write(conn.topic, conn.msgtype, store.deserialize_cdr(data, conn.msgtype),
                      timestamp + after_ms.get(conn.topic, 0) * MS)
    return path


def test_outputs_go_at_the_left_images_bag_time_as_offline(tmp_path: Path) -> None:
    # A robot's bag logs each input when it came: here the left image 1 ms after the frame's
    # stamp, its camera infos at 2 and 3 ms, the right image last at 4 ms. Offline writes the
    # outputs at the left image's bag time; live wrote them at the right image's (4 ms).
    bag = _relogged(write_stereo_bag(tmp_path / 'src', [{}, {}]), tmp_path / 'in', {
        '/left/image_rect': 1, '/left/camera_info': 2, '/right/camera_info': 3,
        '/right/image_rect': 4,
    })
    outcome, _ = _play(tmp_path, bag)
    assert outcome.exit_code == 0, outcome.message
    written = read_bag(tmp_path / 'out')
    assert len(written) == 6
    for topic, entries in written.items():
        assert [t - START_NS for t, _ in entries] == [1 * MS, 101 * MS], topic


def test_a_looped_bag_loses_no_frame_to_a_node_one_frame_behind(tmp_path: Path) -> None:
    # Three frames, then the same three stamps again (a looped bag). The node answers one
    # frame behind: when the last frame before the loop is answered, the first one after it
    # (a smaller stamp, published later) was given up as "older": dropped 1, 5 of 6 processed.
    frames = [dict(stamp=START_NS + i * 10**8, logged=START_NS + k * 10**8)
              for k, i in enumerate([0, 1, 2, 0, 1, 2])]
    bag = write_stereo_bag(tmp_path / 'in', frames, ground_truth=False)
    options = live_options(tmp_path, bag)
    store = jazzy_typestore()
    pairs: list[tuple[int, dict[str, Any], int]] = []
    with InputBag(bag) as source:
        plan = plan_topics(source, options, lambda _: None)
        items: dict[str, Any] = {}
        for topic, kind, timestamp, raw in source.messages(list(plan.inputs.values())):
            msg = store.deserialize_cdr(raw, kind)
            items[plan.key_of[topic]] = msg
            if len(items) == 4:
                pairs.append((stamp_to_ns(msg.header.stamp), items, timestamp))
                items = {}
    session = ReplaySession(options, plan, lambda _: None)
    recorder = live._Recorder(session, store, options, queue.Queue())
    pipeline = StereoPipeline(options.pipeline)

    def answer(index: int) -> None:
        _, frame, _ = pairs[index]
        left, right, geometry = stereo_inputs(frame)
        outputs = node_outputs(pipeline.process(left, right), geometry, left.shape[:2],
                               frame['left'].header, options.pipeline,
                               left_info=frame['left_info'])
        for name, _, raw in outputs.messages:
            recorder._handle(name, raw, time.monotonic(), Progress(1, stream=io.StringIO()))

    with session:
        for index, (stamp, frame, timestamp) in enumerate(pairs):
            recorder.expect(SimpleNamespace(stamp_ns=stamp, items=frame), index, timestamp)
            session.counts['pairs'] += 1
            if index:
                answer(index - 1)
        answer(len(pairs) - 1)
    assert recorder.unanswered() == 0
    assert [score.frame for score in session.report.frames] == [0, 1, 2, 3, 4, 5]


class _DyingNode:
    """A started node that exits once ``player.sent`` reaches ``after`` messages."""

    def __init__(self, after: int) -> None:
        self.after = after
        self.player: _Player | None = None

    @property
    def exit_code(self) -> int | None:
        assert self.player is not None
        return 1 if self.player.sent >= self.after else None

    def last_lines(self) -> str:
        return 'Segmentation fault'


def test_a_node_that_exits_ends_the_replay_at_once(tmp_path: Path) -> None:
    # The node dies after the first pair: the replay went on publishing the whole bag at its
    # recorded pace (here 8 pairs, 4 messages each: all 32) and only then said so.
    bag = write_stereo_bag(tmp_path / 'in', [{}] * 8, ground_truth=False)
    node = _DyingNode(after=4)
    original = _Player.__init__

    def init(self: _Player, *args: Any, **kwargs: Any) -> None:
        original(self, *args, **kwargs)
        node.player = self

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(_Player, '__init__', init)
        outcome, player = _play(tmp_path, bag, '--rate-scale', '4', node=node,
                                silent=set(range(8)))
    assert outcome.exit_code == 2
    assert 'cva-node exited with code 1: Segmentation fault' in outcome.message
    assert player.sent <= 5  # the pair it died on, and at most one message more
    assert outcome.report.counts['dropped'] == outcome.report.counts['pairs'] == 1


def test_outputs_received_before_a_ctrl_c_are_recorded(tmp_path: Path) -> None:
    # Ctrl-C right after the node answered the second pair: its outputs had come but were
    # left in the queue, so the report counted the pair as dropped by the node (1 processed,
    # 1 dropped) and the output bag lacked it.
    bag = write_stereo_bag(tmp_path / 'in', [{}, {}, {}])

    def ctrl_c(_: _Player, index: int) -> None:
        if index == 1:
            os.kill(os.getpid(), signal.SIGINT)

    outcome, _ = _play(tmp_path, bag, answered=ctrl_c)
    assert outcome.exit_code == 130
    counts = outcome.report.counts
    assert (counts['pairs'], counts['processed'], counts['dropped']) == (2, 2, 0)
    assert [score.frame for score in outcome.report.frames] == [0, 1]
    assert len(read_bag(tmp_path / 'out')['/disparity']) == 2


def test_latency_runs_from_the_last_input_of_an_approximate_pair(tmp_path: Path) -> None:
    # Approximate sync: the right image and info are stamped 20 ms after the left ones and
    # logged 300 ms later. The latency ran from the left image's publication (the set's stamp),
    # so it held those 300 ms although the node answered at once.
    source = write_stereo_bag(tmp_path / 'src', [{'stamp_right': START_NS + 20 * MS}])
    bag = _relogged(source, tmp_path / 'in', {'/right/image_rect': 300, '/right/camera_info': 300})
    outcome, _ = _play(tmp_path, bag, '--approximate-sync', '--sync-tolerance', '0.05')
    assert outcome.exit_code == 0, outcome.message
    [score] = outcome.report.frames
    assert score.latency_ms is not None and 0 <= score.latency_ms < 250


def test_publish_times_of_a_pair_are_not_kept(tmp_path: Path) -> None:
    # Approximate mode: only the set's own stamp was taken back; the publish times of its
    # other stamps (and of messages that never paired) stayed, a few entries a frame for the
    # whole run.
    options = live_options(tmp_path, write_stereo_bag(tmp_path / 'in', [{}]))
    store = jazzy_typestore()
    with InputBag(options.bag) as source:
        plan = plan_topics(source, options, lambda _: None)
        items = {plan.key_of[t]: store.deserialize_cdr(raw, kind)
                 for t, kind, _, raw in source.messages(list(plan.inputs.values()))}
    recorder = live._Recorder(
        ReplaySession(options, plan, lambda _: None), store, options, queue.Queue()
    )
    for stamp in (5, 10, 12, 13):
        recorder.published(stamp)
    stamps = {'left': 10, 'right': 12, 'left_info': 10, 'right_info': 13}
    recorder.expect(SimpleNamespace(stamp_ns=10, stamps_ns=stamps, items=items), 0, 10)
    assert recorder.publish_times == {}


def test_an_answered_pair_without_geometry_is_skipped_not_lost(tmp_path: Path) -> None:
    # Camera infos of another size than the images: the replay has no geometry for the pair.
    # A node that answers it all the same (one already running, --no-start-node) had the
    # frame answered but neither processed nor skipped: 1 pair, 0 + 0 + 0 dropped.
    bad = write_stereo_bag(tmp_path / 'bad', [{'info_size': (44, 30)}], ground_truth=False)
    good = write_stereo_bag(tmp_path / 'good', [{}], ground_truth=False)
    options = live_options(tmp_path, bad)
    store = jazzy_typestore()

    def first_pair(path: Path) -> dict[str, Any]:
        with InputBag(path) as source:
            plan = plan_topics(source, options, lambda _: None)
            return {plan.key_of[t]: store.deserialize_cdr(raw, kind)
                    for t, kind, _, raw in source.messages(list(plan.inputs.values()))}

    with InputBag(bad) as source:
        plan = plan_topics(source, options, lambda _: None)
    logs: list[str] = []
    session = ReplaySession(options, plan, logs.append)
    recorder = live._Recorder(session, store, options, queue.Queue())
    frame = first_pair(good)
    left, right, geometry = stereo_inputs(frame)
    outputs = node_outputs(StereoPipeline(options.pipeline).process(left, right), geometry,
                           left.shape[:2], frame['left'].header, options.pipeline,
                           left_info=frame['left_info'])
    with session:
        recorder.expect(SimpleNamespace(stamp_ns=START_NS, items=first_pair(bad)), 0, START_NS)
        session.counts['pairs'] = 1
        for name, _, raw in outputs.messages:
            recorder._handle(name, raw, time.monotonic(), Progress(1, stream=io.StringIO()))
    counts = session.counts
    assert recorder.unanswered() == 0
    assert (counts['processed'], counts['skipped']) == (0, 1)
    assert any(line.startswith('skipped outputs of frame 0: ') and '44' in line for line in logs)


def test_a_replay_behind_its_schedule_handles_the_outputs_as_they_come(tmp_path: Path) -> None:
    # --rate-scale 1000: each message is due before the replay gets to it, and the outputs
    # were handled only while waiting for a message's time: here never until the bag's end.
    # They piled up in the queue (6 messages a frame: 6, 12, ... 30), and ground truth does
    # not wait that long: of 130 such frames the first 30 went unscored.
    waiting: list[int] = []
    outcome, _ = _play(tmp_path, write_stereo_bag(tmp_path / 'in', [{}] * 5),
                       '--rate-scale', '1000',
                       answered=lambda player, _: waiting.append(player.received.qsize()))
    assert outcome.exit_code == 0, outcome.message
    assert waiting == [6] * 5
    assert [score.auc is not None for score in outcome.report.frames] == [True] * 5



def test_messages_waiting_at_ctrl_c_are_listed_with_the_count(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # As offline: frame 1 never pairs (its right side is 1 µs off) and waits when the signal
    # comes. Live counted its four messages unpaired but listed none.
    step = 100 * MS
    bag = write_stereo_bag(tmp_path / 'in', [
        {'gt_lag': step + step // 2},
        {'stamp_right': START_NS + step + 1000, 'no_gt': True},
        {},
    ])
    add_ground_truth = ReplaySession.add_ground_truth

    def signal_on_truth(session: ReplaySession, stamp: int, msg: Any) -> None:
        if stamp == START_NS:
            os.kill(os.getpid(), signal.SIGINT)
        add_ground_truth(session, stamp, msg)

    monkeypatch.setattr(ReplaySession, 'add_ground_truth', signal_on_truth)
    outcome, _ = _play(tmp_path, bag)
    assert outcome.exit_code == 130
    report = outcome.report
    assert report.counts['unpaired'] == sum(report.unpaired_by_topic.values()) == 4
    assert {m['reason'] for m in report.unpaired} == {
        'still waiting for its partners when the run stopped'
    }


def test_an_unreadable_input_message_is_no_skipped_pair(tmp_path: Path) -> None:
    # A left image cut short: counted 'unreadable', not 'skipped' (skipped counts pairs).
    source = write_stereo_bag(tmp_path / 'raw', [{}, {}, {}])
    bag = tmp_path / 'in'
    with InputBag(source) as src, OutputBag(bag, 'mcap', jazzy_typestore()) as dst:
        for topic, msgtype, timestamp, raw in src.messages(list(src.topics)):
            cut = topic == '/left/image_rect' and timestamp == START_NS + 100 * MS
            dst.write(topic, msgtype, bytes(raw)[:10] if cut else bytes(raw), timestamp)
    outcome, _ = _play(tmp_path, bag)
    counts = outcome.report.counts
    assert counts['unreadable'] == 1 and counts['skipped'] == 0
    assert (counts['pairs'], counts['processed']) == (2, 2)
