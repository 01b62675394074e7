"""Review regressions (36): the PNGs as a reader looks at them — ROC curves of a scene without
errors and the legend's place, titles that name the matcher and a partial run, the replay's
confidence maps on a fixed [0, 1] scale, its over-time plots of one frame and of long bags,
and the Table-1 PNG's title."""

from __future__ import annotations

import cv2
from matplotlib.figure import Figure
import numpy as np
import pytest

from cva_confidence_ros import plots
from cva_confidence_ros.datasets import StereoSample
from cva_confidence_ros.evaluation import table1
from cva_confidence_ros.evaluation.scene import evaluate_scene
from msg_tools.scoring import FrameScore, ReplayReport, ReportWriter

D = 16
CONFIG = {'matcher': 'census_bm', 'confidence_method': 'cva_net_fast',
          'confidence_threshold': 0.5}


@pytest.fixture
def figures(monkeypatch) -> list[Figure]:
    """Every matplotlib figure saved while the test runs, drawn (renderer ready)."""
    saved: list[Figure] = []
    original = Figure.savefig

    def savefig(self, *args, **kwargs):
        saved.append(self)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Figure, 'savefig', savefig)
    return saved


def _inside(inner, outer, slack: float = 0.5) -> bool:
    return (inner.x0 >= outer.x0 - slack and inner.x1 <= outer.x1 + slack
            and inner.y0 >= outer.y0 - slack and inner.y1 <= outer.y1 + slack)


# --- plots.save_roc_curves -------------------------------------------------------------------


def test_roc_of_a_scene_without_errors_is_drawn_off_the_axis_and_said(tmp_path, figures):
    density = np.linspace(0.05, 1.0, 20)
    plots.save_roc_curves({'pkrn': (density, np.zeros(20))}, tmp_path / 'roc.png',
                          error_rate=0.0, title='all correct')
    axes = figures[-1].axes[0]
    # Before: y from 0 exactly, so both curves lay on (under) the bottom spine, half clipped,
    # and nothing said why the plot looked empty.
    assert axes.get_ylim()[0] < 0.0
    assert any('no wrong disparities' in t.get_text() for t in axes.texts)


def test_roc_legend_leaves_a_flat_curve_visible(tmp_path, figures):
    density = np.linspace(0.05, 1.0, 20)
    curves = {'uninformative': (density, np.full(20, 0.09)),
              'good': (density, np.linspace(0.0, 0.09, 20))}
    plots.save_roc_curves(curves, tmp_path / 'roc.png', error_rate=0.09)
    figure = figures[-1]
    axes = figure.axes[0]
    box = axes.get_legend().get_window_extent(figure.canvas.get_renderer())
    flat = axes.get_lines()[0]
    points = flat.get_transform().transform(np.column_stack(flat.get_data()))
    # Before: legend at 'upper left', on top of the flat line at ε (a method no better than
    # chance was hidden behind its own name).
    covered = [(x, y) for x, y in points if box.x0 <= x <= box.x1 and box.y0 <= y <= box.y1]
    assert covered == []


# --- evaluation.scene: roc.png ---------------------------------------------------------------


class _Ramp:
    needs_right = False

    def __call__(self, inputs):
        height, width = inputs.disparity.shape
        return np.tile(np.linspace(0.0, 1.0, width, dtype=np.float32), (height, 1))


def test_scene_roc_title_names_the_matcher(tmp_path, monkeypatch):
    titles: list[str | None] = []
    original = plots.save_roc_curves

    def record(curves, path, error_rate=None, title=None):
        titles.append(title)
        return original(curves, path, error_rate=error_rate, title=title)

    monkeypatch.setattr(plots, 'save_roc_curves', record)
    rng = np.random.default_rng(36)
    texture = rng.integers(0, 256, (32, 68), dtype=np.uint8)
    gt = np.full((32, 64), 4.0, dtype=np.float32)
    sample = StereoSample('synthetic', 'shift4', np.ascontiguousarray(texture[:, :64]),
                          np.ascontiguousarray(texture[:, 4:]), gt)
    evaluate_scene(sample, 'census_bm', {'ramp': _Ramp()}, max_disparity=D,
                   plot_dir=tmp_path / 'plots')
    # Before: 'synthetic/shift4  ε = …' — which matcher, once the PNG is in a report?
    assert titles and 'census_bm' in (titles[0] or '')


# --- msg_tools.scoring: the replay's PNGs ----------------------------------------------------


def test_replay_draws_a_network_confidence_on_a_fixed_0_to_1_scale(tmp_path):
    rng = np.random.default_rng(0)
    easy = rng.uniform(0.5, 1.0, (40, 60)).astype(np.float32)
    hard = rng.uniform(0.0, 1.0, (40, 60)).astype(np.float32)
    easy[0, 0] = hard[0, 0] = 0.9
    writer = ReportWriter(tmp_path / 'report')
    for frame, confidence in enumerate((easy, hard)):
        writer.frame_plots(FrameScore(frame=frame, stamp_ns=frame), confidence, 'cva_net_fast')
    greys = [int(cv2.imread(str(tmp_path / 'report' / f'confidence_{f:05d}.png'))[0, 0, 0])
             for f in (0, 1)]
    # Before: the easy frame (1st percentile above 0.25) was stretched over its own 1–99 %
    # range, 0.9 drawn 206 there and 230 in the other frame: the maps did not compare.
    assert greys == [round(0.9 * 255)] * 2


def test_auc_over_time_of_one_frame_shows_every_line_on_whole_frames(tmp_path, figures):
    report = ReplayReport(config=CONFIG, frames=[FrameScore(
        frame=0, stamp_ns=0, auc=0.05, auc_opt=0.03, error_rate=0.2, kept_fraction=0.6)])
    ReportWriter(tmp_path / 'report').write(report)
    figure = next(f for f in figures if any(
        line.get_label() == 'AUC opt' for a in f.axes for line in a.get_lines()))
    axes = figure.axes[0]
    # Before: 'AUC opt' and 'error rate' were lines without markers (one point: invisible),
    # the frame axis ticked -0.04 … 0.04, and no title said which matcher and method.
    assert all(line.get_marker() not in (None, 'None', '') for line in axes.get_lines())
    ticks = [t for t in axes.get_xticks() if axes.get_xlim()[0] <= t <= axes.get_xlim()[1]]
    assert ticks and all(float(t).is_integer() for t in ticks)
    assert 'census_bm' in axes.get_title() and 'cva_net_fast' in axes.get_title()


def test_least_kept_label_stays_inside_the_plot_at_the_end_of_a_long_bag(tmp_path, figures):
    frames = [FrameScore(frame=i, stamp_ns=i, kept_fraction=0.9 - i / 2000) for i in range(1200)]
    ReportWriter(tmp_path / 'report').write(ReplayReport(config=CONFIG, frames=frames))
    figure = next(f for f in figures if len(f.axes) == 2)
    kept_axes = figure.axes[0]
    renderer = figure.canvas.get_renderer()
    (label,) = [t for t in kept_axes.texts if 'least kept' in t.get_text()]
    # Before: written rightwards from the line at frame 1199, over the axes' frame and to the
    # figure's edge (a five-digit frame number was cut off).
    assert _inside(label.get_window_extent(renderer), kept_axes.get_window_extent(renderer))


# --- evaluation.table1: table1.png -----------------------------------------------------------


def test_table1_png_holds_its_whole_title_with_a_single_method(tmp_path):
    records = [{'row': 'Middlebury v3', 'scene': 'S0', 'matcher': 'census_bm',
                'method': 'pkrn', 'auc': 0.15, 'auc_opt': 0.07}]
    title = 'Table 1 reproduction (develop, D = 64): AUC × 10², mean over scenes'
    path = table1.save_table_png(records, [table1.TableRow('Middlebury v3', 'middlebury2014')],
                                 ['census_bm'], tmp_path / 'table1.png', title,
                                 [('pkrn', 'PKRN')])
    grey = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    border = np.concatenate([grey[:2].ravel(), grey[-2:].ravel(), grey[:, :2].ravel(),
                             grey[:, -2:].ravel()])
    # Before: a 5-inch figure for one method, the title ran off its right edge ("…, mea"):
    # dark text pixels in the last columns. Nothing drawn may touch the PNG's edge.
    assert border.min() >= 250
