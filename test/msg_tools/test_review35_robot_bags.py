"""Review 35: bags as robots record them, replayed with ``cva-bag-replay``.

Ground truth from a node whose latency varies comes a little out of stamp order in the bag;
one such message used to start a new ordering epoch (as a jump back of the stamps does), after
which no later frame was scored.
"""

from __future__ import annotations

from pathlib import Path

from msg_test_utils import START_NS, replay_offline, write_stereo_bag
import pytest

FRAME_NS = 100_000_000


def _scored(report: dict) -> dict[int, bool]:
    return {f['frame']: f['auc'] is not None for f in report['frames']}


def test_ground_truth_a_little_out_of_order_does_not_unscore_the_rest(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The ground truth of frame 1 is logged 150 ms after its images, after that of frame 2.
    # Before: its stamp, before the last one, counted as a jump back and frames 3-7 went
    # unscored ('no ground truth with this stamp in the bag'): 2 of 8 scored. Frame 1 itself
    # waits for its ground truth (less than 1 s of stamps after frame 2's): all 8 scored.
    frames = [{'gt_lag': 150_000_000} if i == 1 else {} for i in range(8)]
    bag = write_stereo_bag(tmp_path / 'in', frames)
    code, err, report = replay_offline(bag, tmp_path, capsys)
    assert code == 0
    assert all(_scored(report).values()) and len(_scored(report)) == 8
    assert report['summary']['gt_unmatched'] == 0
    assert 'not scored' not in err


def test_ground_truth_of_a_late_frame_does_not_unscore_the_rest(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Frames 1 and 2 logged in swapped order (stamps 200 ms, then 100 ms): the synchroniser
    # lets the late one go, as the node does, and its ground truth is out of order too.
    # Before: frame 3 went unscored.
    stamps = [0, 2, 1, 3]
    frames = [{'stamp': START_NS + s * FRAME_NS, 'logged': START_NS + i * FRAME_NS}
              for i, s in enumerate(stamps)]
    bag = write_stereo_bag(tmp_path / 'in', frames)
    code, err, report = replay_offline(bag, tmp_path, capsys)
    assert code == 0
    assert [f['stamp_ns'] for f in report['frames']] == [
        START_NS + s * FRAME_NS for s in (0, 2, 3)]
    assert all(_scored(report).values())
    assert report['summary']['gt_unmatched'] == 1  # that of the frame let go
    assert 'not scored' not in err


def test_a_folder_without_metadata_names_its_storage_files(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # `ros2 bag record` killed before it wrote metadata.yaml: the folder holds the storage
    # files of a split recording. Before: 'Expected metadata file ... does not exist.' and no
    # word of the files, which can be replayed one by one.
    bag = write_stereo_bag(tmp_path / 'in', [{}, {}])
    (bag / 'metadata.yaml').unlink()
    (bag / 'in.mcap').rename(bag / 'rec_0.mcap')
    (bag / 'rec_1.mcap').write_bytes((bag / 'rec_0.mcap').read_bytes())
    code, err, _ = replay_offline(bag, tmp_path, capsys)
    assert code == 2
    assert f'holds the storage files {bag / "rec_0.mcap"}, {bag / "rec_1.mcap"}' in err
    assert f'ros2 bag reindex {bag}' in err
    # As it says: one file given as the bag replays.
    code, err, report = replay_offline(bag / 'rec_0.mcap', tmp_path, capsys)
    assert code == 0 and report['summary']['processed'] == 2


def test_an_mcap_file_cut_short_says_how_to_recover_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A recording killed mid-way leaves an MCAP file without summary and footer. Before:
    # only 'ReaderError: File end magic is invalid.'
    bag = write_stereo_bag(tmp_path / 'in', [{}, {}])
    data = (bag / 'in.mcap').read_bytes()
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(data[: len(data) * 2 // 3])
    code, err, _ = replay_offline(cut, tmp_path, capsys)
    assert code == 2
    assert 'does not end like an MCAP file' in err
    assert f'mcap recover {cut} -o {tmp_path / "cut_recovered.mcap"}' in err


@pytest.mark.parametrize('transport', ['raw', 'png'])
def test_a_missing_input_topic_names_the_stereo_cameras_of_the_bag(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], transport: str
) -> None:
    # A robot's bag: the camera under a namespace (raw, or image_transport's compressed).
    # Before: the error listed every topic of the bag and left the user to find the
    # namespace; now it names the options of each stereo camera it holds, and they work.
    frame = {} if transport == 'raw' else {'transport': transport}
    bag = write_stereo_bag(tmp_path / 'in', [frame, frame], prefix='/robot1/front_stereo')
    code, err, _ = replay_offline(bag, tmp_path, capsys)
    assert code == 2
    option = '--topic-prefix /robot1/front_stereo'
    if transport != 'raw':
        option += (' --left-topic left/image_rect/compressed '
                   '--right-topic right/image_rect/compressed')
    assert err.rstrip().endswith(f'; stereo cameras in the bag: {option}')
    code, err, report = replay_offline(bag, tmp_path, capsys, *option.split())
    assert code == 0 and report['summary']['processed'] == 2
