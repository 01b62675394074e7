"""Review 34 of ``cva-bag-replay``: every configuration error names the option the user typed.

Only the errors of ``ReplayOptions`` and ``TopicNames`` named their options; those of the
pipeline (``--downsample 3``: 'downsample must be 1, 2 or 4'), of the scan (``--scan-height
2 1``: 'scan_min_height must be < scan_max_height') and live mode's check of the ranges the node
declares (``--queue-size 100000``) named only the field or node parameter. A
:class:`ConfigError` now carries the names of the values at fault (``fields``), and the
command line puts its options in front.
"""

from __future__ import annotations

from pathlib import Path
import pickle

from msg_test_utils import MAX_DISPARITY, write_stereo_bag
import pytest

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.pipeline import PipelineConfig
from cva_confidence_ros.scan import ScanConfig
from msg_tools.bag_replay import build_parser, main, name_options, options_from_args


def _argv(tmp_path: Path, *extra: str, bag: Path | None = None) -> list[str]:
    return [
        str(bag or tmp_path / 'missing_bag'), '--out', str(tmp_path / 'out'),
        '--report', str(tmp_path / 'report'), *extra,
    ]


@pytest.mark.parametrize(('extra', 'start'), [
    (('--scan-height', '2', '1'), '--scan-height: scan_min_height must be < scan_max_height'),
    (('--scan-range', '5', '1'), '--scan-range: scan ranges must satisfy'),
    (('--scan-pitch', '3'), '--scan-pitch: scan_pitch must be in (-pi/2, pi/2)'),
    (('--confidence-threshold', '2'), '--confidence-threshold: confidence_threshold must be'),
    (('--downsample', '3'), '--downsample: downsample must be 1, 2 or 4; got 3'),
    (('--roi', '0.9', '0.1'), '--roi: roi_top must be smaller than roi_bottom'),
    (('--speckle-size', '-1'), '--speckle-size: speckle_size must be an integer in'),
    (('--speckle-range', '-2'), '--speckle-range: speckle_range must be a number in'),
    (('--tile-budget-mb', '0'), '--tile-budget-mb: tile_budget_mb must be a finite number'),
    (('--device', 'cux'), "--device: device must be one of ('cpu', 'cuda', 'auto')"),
    (('--matcher', 'foo'), "--matcher: unknown matcher 'foo'"),
    (('--confidence-method', 'x'), "--confidence-method: unknown confidence_method 'x'"),
    (('--max-disparity', '0'), '--max-disparity: max_disparity must be an integer in'),
    (('--scan-height', 'nan', '1'), '--scan-height: scan_min_height must be a finite number'),
    # Named once before (one option at a time); now through the same fields.
    (('--jpeg-quality', '0'), '--jpeg-quality: overlay_jpeg_quality must be an integer'),
    (('--rate-scale', '0'), '--rate-scale: rate_scale must be a finite number > 0'),
])
def test_offline_errors_name_the_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: tuple[str, ...], start: str
) -> None:
    # Refused before the (missing) bag is opened, on one line.
    code = main(_argv(tmp_path, *extra))
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith(f'cva-bag-replay: error: {start}'), err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / 'out').exists() and not (tmp_path / 'report').exists()
    # The Python API of the command line names them the same way.
    with pytest.raises(ConfigError) as caught:
        options_from_args(build_parser().parse_args(_argv(tmp_path, *extra)))
    assert str(caught.value).startswith(start)


@pytest.mark.parametrize(('extra', 'start'), [
    (('--queue-size', '100000'),
     '--queue-size: queue_size must be in [1, 1000] (the range the node declares); got 100000'),
    (('--approximate-sync', '--sync-tolerance', '100'),
     '--sync-tolerance: approximate_sync_tolerance_seconds must be in [0, 10]'),
    (('--tile-budget-mb', '1e9'), '--tile-budget-mb: tile_budget_mb must be in [1, '),
])
def test_live_range_errors_name_the_option(
    tmp_path: Path, extra: tuple[str, ...], start: str
) -> None:
    # Valid options, but outside the ranges the node declares: node_arguments refuses them
    # (no node, no DDS) by the node parameter; the command line's mapping names the option.
    from msg_tools.live import node_arguments

    options = options_from_args(build_parser().parse_args(
        _argv(tmp_path, '--mode', 'live', *extra)
    ))
    with pytest.raises(ConfigError) as caught:
        node_arguments(options, 'n')
    assert not str(caught.value).startswith('--')  # the node's own name for it, as before
    assert str(name_options(caught.value)).startswith(start)


def test_a_live_run_names_the_option_before_the_old_report_goes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = write_stereo_bag(tmp_path / 'in', [{}])
    report = tmp_path / 'report'
    report.mkdir()
    (report / 'report.json').write_text('{"old": true}')
    code = main(_argv(tmp_path, '--mode', 'live', '--max-disparity', str(MAX_DISPARITY),
                      '--confidence-method', 'pkrn', '--queue-size', '100000', '--overwrite',
                      bag=bag))
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith('cva-bag-replay: error: --queue-size: queue_size must be in'), err
    assert (report / 'report.json').read_text() == '{"old": true}'
    assert not (tmp_path / 'out').exists()


def test_config_error_fields() -> None:
    plain = ConfigError('x')
    assert plain.fields == () and str(plain) == 'x' and plain.args == ('x',)
    named = ConfigError('bad band', 'scan_min_height', 'scan_max_height')
    assert named.fields == ('scan_min_height', 'scan_max_height') and str(named) == 'bad band'
    again = pickle.loads(pickle.dumps(named))
    assert (type(again), str(again), again.fields) == (ConfigError, 'bad band', named.fields)
    assert pickle.loads(pickle.dumps(plain)).fields == ()
    # The library's classes fill them in; their messages are unchanged.
    with pytest.raises(ConfigError, match=r'^roi_top must be smaller') as caught:
        PipelineConfig(roi_top=0.9, roi_bottom=0.1)
    assert caught.value.fields == ('roi_top', 'roi_bottom')
    with pytest.raises(ConfigError, match=r'^scan_pitch must be') as caught:
        ScanConfig(pitch=3.0)
    assert caught.value.fields == ('scan_pitch',)


def test_node_side_errors_keep_the_parameter_names() -> None:
    from cva_confidence_ros.ros.params import NodeConfig, check_declared_ranges

    with pytest.raises(ConfigError, match=r'^queue_size must be >= 1; got 0$') as caught:
        NodeConfig(queue_size=0)
    assert caught.value.fields == ('queue_size',)
    with pytest.raises(ConfigError, match=r'^scan ranges must satisfy') as caught:
        NodeConfig(scan_range_min=5.0, scan_range_max=1.0)
    assert caught.value.fields == ('scan_range_min', 'scan_range_max')
    with pytest.raises(ConfigError, match=r'^max_disparity must be in') as caught:
        check_declared_ranges({'max_disparity': 100000})
    assert caught.value.fields == ('max_disparity',)


def test_name_options() -> None:
    # Each option once, in the order of the fields.
    named = name_options(ConfigError('m', 'roi_top', 'roi_bottom'))
    assert str(named) == '--roi: m' and named.fields == ()
    named = name_options(ConfigError('m', 'compressed_depth_quantization', 'compressed_depth_max'))
    assert str(named) == '--compressed-depth-quantization, --compressed-depth-max: m'
    # No fields, or one the command line does not set: the error as it is.
    for err in (ConfigError('m'), ConfigError('m', 'image_transport'),
                ConfigError('m', 'queue_size', 'input_qos')):
        assert name_options(err) is err
