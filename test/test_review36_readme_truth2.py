"""README claims of "Offline: bags and evaluation", against the code.

Each test pins a sentence that said something the tools do not do (or no longer only do), next
to the behaviour the corrected sentence describes.
"""

from __future__ import annotations

import inspect
import json
from pathlib import Path
import re

import cv2
import numpy as np

from cva_confidence_ros.datasets.synthetic import synthetic_pair

README = Path(__file__).resolve().parent.parent / 'README.md'


def _readme() -> str:
    """The README with its line breaks, runs of spaces and comment marks as single spaces."""
    return re.sub(r'\s+(# )?', ' ', README.read_text(encoding='utf-8'))


def _stereo_folder(root: Path, seeds: list[int], size: tuple[int, int] = (48, 64),
                   max_disparity: int = 16) -> Path:
    """stereo_folder scenes ``scene<seed>`` of synthetic pairs under ``root``."""
    for seed in seeds:
        sample = synthetic_pair(seed, *size, max_disparity)
        folder = root / f'scene{seed}'
        folder.mkdir(parents=True)
        cv2.imwrite(str(folder / 'left.png'), sample.left)
        cv2.imwrite(str(folder / 'right.png'), sample.right)
        np.save(folder / 'disparity.npy', sample.disparity.astype(np.float32))
    return root


def test_evaluate_table_is_a_mean_over_scenes_not_per_scene(tmp_path: Path, capsys):
    # The README called cva-evaluate's table "per-scene": it has one row per data set and
    # matcher (the mean over the scenes); the per-scene values are the JSON records.
    from cva_confidence_ros.evaluation.cli import main

    root = _stereo_folder(tmp_path / 'data', [1, 2])
    out = tmp_path / 'eval'
    assert main(['--data-root', str(root), '--dataset', 'stereo_folder', '--matchers',
                 'census_bm', '--methods', 'pkrn', '--max-disparity', '16', '--json',
                 str(tmp_path / 'eval.json'), '--out', str(out)]) == 0
    capsys.readouterr()
    records = json.loads((tmp_path / 'eval.json').read_text())
    assert sorted(r['scene'] for r in records) == ['scene1', 'scene2']
    rows = [line for line in (out / 'table.md').read_text().splitlines()
            if line.startswith('| stereo_folder')]
    assert len(rows) == 1
    mean = 100 * np.mean([r['auc'] for r in records])
    assert f'{mean:.2f}' in rows[0]
    text = _readme()
    assert 'per-scene AUC table' not in text
    assert "AUC table in the layout of the paper's Table 1 (mean over scenes), per-scene JSON" \
        in text


def test_replay_closing_line_names_only_the_frame_kept_least(tmp_path: Path, capsys):
    # The README said the closing line names the frame with the highest predicted error too,
    # as summary.md does; it names the frame kept least and the mean predicted error only.
    from msg_tools.bag_from_dataset import main as bag_from_dataset
    from msg_tools.bag_replay import main as replay

    root = _stereo_folder(tmp_path / 'data', [1, 2], size=(48, 96))
    bag = tmp_path / 'bag'
    assert bag_from_dataset(['--data-root', str(root), '--dataset', 'stereo_folder',
                             '--out', str(bag)]) == 0
    report = tmp_path / 'report'
    assert replay([str(bag), '--out', str(tmp_path / 'out'), '--report', str(report),
                   '--confidence-method', 'cva_net_fast', '--device', 'cpu',
                   '--max-plots', '0']) == 0
    out = capsys.readouterr().out
    summary = json.loads((report / 'report.json').read_text())['summary']
    assert summary['predicted_kept_error'] is not None
    closing = next(line for line in out.splitlines() if 'predicted error of the kept' in line)
    assert f"in frame {summary['min_kept_fraction_frame']})" in closing
    assert closing.count('frame ') == 1  # no frame named for the highest predicted error
    worst = summary['max_predicted_kept_error_frame']
    assert f'(frame {worst})' in (report / 'summary.md').read_text()
    text = _readme()
    assert 'and so does the closing line' not in text
    assert 'with the highest predicted error; the closing line names the frame kept least' in text


def test_left_out_scenes_are_named_by_bag_from_dataset_and_train_too(tmp_path: Path, capsys):
    # Since today cva-bag-from-dataset and cva-train name the scenes a partial download leaves
    # out, as cva-evaluate and cva-table1 do; the README named only the latter two.
    from cva_confidence_ros.training import trainer
    from msg_tools.bag_from_dataset import main as bag_from_dataset

    root = _stereo_folder(tmp_path / 'data', [1])
    partial = root / 'scene9'
    partial.mkdir()
    source = root / 'scene1'
    for name in ('left.png', 'disparity.npy'):  # the right image not downloaded
        (partial / name).write_bytes((source / name).read_bytes())
    assert bag_from_dataset(['--data-root', str(root), '--dataset', 'stereo_folder',
                             '--out', str(tmp_path / 'bag')]) == 0
    assert 'stereo_folder: 1 scene(s) left out, a file missing: scene9' in capsys.readouterr().err
    assert 'skipped_notice(' in inspect.getsource(trainer._load_samples)
    text = _readme()
    assert ('is left out, and `cva-evaluate`, `cva-table1`, `cva-train` and '
            '`cva-bag-from-dataset` name it with the file') in text


def test_table1_reuse_marks_records_so_its_json_is_not_byte_identical():
    # "a resumed --json ends byte-identical" holds for cva-evaluate --resume; cva-table1
    # --reuse marks each record it took over, so its table1.json differs from a straight run's.
    from cva_confidence_ros.evaluation import table1

    assert "'reused': True" in inspect.getsource(table1)
    text = _readme()
    assert ("byte-identical to an uninterrupted run's (`table1.json` marks the records taken "
            'over `"reused": true`)') in text


def test_replay_compressed_depth_quantization_help_says_about():
    # The help promised "within z^2 / (Q (Q + 1)) m": the integer code is truncated, and the
    # error reaches z² / (A − z), A = Q (Q + 1), a little more (as the README now says).
    from std_msgs.msg import Header

    from cva_confidence_ros.ros.convert import depth_to_image
    from cva_confidence_ros.ros.transport import (
        compressed_depth_to_array,
        depth_image_to_compressed_depth,
    )
    from msg_tools.bag_replay import build_parser

    q = 100.0  # the default --compressed-depth-quantization
    depth = np.linspace(9.0, 9.99, 2000, dtype=np.float32)[None]
    message = depth_image_to_compressed_depth(depth_to_image(depth, Header(), '32FC1'))
    error = np.abs(compressed_depth_to_array(message).astype(np.float64) - depth)
    assert (error > depth.astype(np.float64) ** 2 / (q * (q + 1.0))).any()
    help_text = re.sub(r'\s+', ' ', build_parser().format_help())
    assert 'comes back within about z^2 / (Q (Q + 1)) m (default 100.0)' in help_text
