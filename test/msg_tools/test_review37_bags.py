"""Review 37: a robotics engineer's bags through ``cva-bag-replay`` (per-frame ROC titles,
interrupted runs, output bags read back, odd input bags)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from msg_test_utils import MAX_DISPARITY, START_NS, replay_offline, write_stereo_bag
import pytest


def test_frame_roc_png_names_run_frame_and_stamp(tmp_path: Path, monkeypatch: Any) -> None:
    """roc_<frame>.png named neither matcher nor stamp: two runs' PNGs looked alike."""
    from cva_confidence_ros import plots
    from msg_tools.bag_replay import main

    titles: list[tuple[list[str], str | None]] = []
    original = plots.save_roc_curves

    def record(curves: Any, path: Any, error_rate: Any = None, title: Any = None) -> Path:
        titles.append((list(curves), title))
        return original(curves, path, error_rate=error_rate, title=title)

    monkeypatch.setattr(plots, 'save_roc_curves', record)
    bag = write_stereo_bag(tmp_path / 'in', [{} for _ in range(2)])
    code = main([
        str(bag), '--out', str(tmp_path / 'out'), '--report', str(tmp_path / 'report'),
        '--matcher', 'census_sgm', '--max-disparity', str(MAX_DISPARITY),
        '--confidence-method', 'pkrn', '--max-plots', '1',
    ])  # fmt: skip
    assert code == 0
    [(labels, title)] = titles
    assert labels == ['pkrn']
    assert title is not None
    assert 'census_sgm + pkrn' in title and f'D = {MAX_DISPARITY}' in title
    assert 'frame 0' in title
    assert f'{START_NS // 10**9}.{START_NS % 10**9:09d} s' in title
    assert (tmp_path / 'report' / 'roc_00000.png').is_file()


@pytest.fixture
def hold_folder() -> Any:
    """Makes another process hold the lock a replay takes on its report folder (as a second
    cva-bag-replay writing there does): ``hold_folder(folder)``."""
    import subprocess
    import sys

    holders = []

    def hold(folder: Path) -> Path:
        folder.mkdir(exist_ok=True)
        holder = subprocess.Popen(
            [sys.executable, '-c',
             'import fcntl, os, sys; fd = os.open(sys.argv[1], os.O_RDONLY); '
             'fcntl.flock(fd, fcntl.LOCK_EX); print("held", flush=True); sys.stdin.read()',
             str(folder)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        )  # fmt: skip
        holders.append(holder)
        assert holder.stdout is not None and holder.stdout.readline().strip() == 'held'
        return folder

    yield hold
    for holder in holders:
        holder.communicate('')


def test_second_replay_into_a_report_folder_being_written_is_refused(
    tmp_path: Path, capsys: Any, hold_folder: Any
) -> None:
    """Two replays into one --report at once both passed the empty-folder check and wrote a
    mix of their PNGs and report files (exit 0 both)."""
    from msg_tools.bag_replay import main

    bag = write_stereo_bag(tmp_path / 'in', [{} for _ in range(2)])
    report = hold_folder(tmp_path / 'report')
    code = main([
        str(bag), '--out', str(tmp_path / 'out'), '--report', str(report),
        '--max-disparity', str(MAX_DISPARITY), '--confidence-method', 'pkrn',
    ])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2
    assert 'being written by another cva-bag-replay' in err and str(report) in err
    assert list(report.iterdir()) == []
    assert not (tmp_path / 'out').exists()


def test_report_folder_taken_after_the_option_checks_is_refused_at_start(
    tmp_path: Path, hold_folder: Any
) -> None:
    """The race: both runs checked the folder before either wrote; the second one's session
    is refused when it starts, before it clears (--overwrite) or writes anything."""
    from cva_confidence_ros.errors import ConfigError
    from msg_tools.bag_replay import build_parser, options_from_args
    from msg_tools.replay import run_offline

    bag = write_stereo_bag(tmp_path / 'in', [{} for _ in range(2)])
    report = tmp_path / 'report'
    options = options_from_args(build_parser().parse_args([
        str(bag), '--out', str(tmp_path / 'out'), '--report', str(report),
        '--max-disparity', str(MAX_DISPARITY), '--confidence-method', 'pkrn', '--overwrite',
    ]))  # fmt: skip
    hold_folder(report)
    (report / 'report.json').write_text('{}')  # the other run's
    with pytest.raises(ConfigError, match='being written by another cva-bag-replay'):
        run_offline(options, log=lambda _: None)
    assert [p.name for p in report.iterdir()] == ['report.json']
    assert not (tmp_path / 'out').exists()


def test_ground_truth_of_frames_skipped_for_a_new_camera_size_is_not_blamed(
    tmp_path: Path, capsys: Any
) -> None:
    """camera_info of another size from frame 3 on: those frames are skipped (logged), but the
    closing line said their ground truth "must carry its left image's stamp" and was "100 ms
    later than frame stamp" of frame 2, sending the user after a stamp fault that is not."""
    from msg_tools.bag_replay import main

    frames: list[dict[str, Any]] = [{} for _ in range(5)]
    for frame in frames[3:]:
        frame['info_size'] = (80, 60)  # the images stay 40×30
    bag = write_stereo_bag(tmp_path / 'in', frames)
    code = main([
        str(bag), '--out', str(tmp_path / 'out'), '--report', str(tmp_path / 'report'),
        '--max-disparity', str(MAX_DISPARITY), '--confidence-method', 'pkrn',
        '--max-plots', '0',
    ])  # fmt: skip
    captured = capsys.readouterr()
    assert code == 0
    assert 'skipped frame 3' in captured.err and '80×60' in captured.err
    line = captured.out.splitlines()[0]
    assert '3 of 5 frames processed, 2 skipped' in line
    assert '2 ground-truth messages' in line
    assert 'the stereo pairs of those stamps were skipped' in line
    assert 'must carry' not in line and 'later than frame stamp' not in line


def test_window_without_frames_is_not_called_an_empty_bag(tmp_path: Path, capsys: Any) -> None:
    """--start/--duration between two frames: "the input topics hold no messages in bag X"
    of a bag full of them; the counts are those of the part replayed."""
    bag = write_stereo_bag(tmp_path / 'in', [{} for _ in range(3)])  # frames 0.1 s apart
    code, err, _ = replay_offline(bag, tmp_path, capsys, '--start', '0.05', '--duration', '0.01')
    assert code == 2
    assert 'hold no messages in the part replayed (from 0.05 s for 0.01 s) of bag' in err
    assert not (tmp_path / 'out').exists()
