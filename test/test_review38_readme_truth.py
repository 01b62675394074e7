"""Review 38: what README and ``--help`` say about today's changes, held by the code.

``cva-train --help`` still said ``--resume`` continues "after its last finished epoch" (it
also goes on within an epoch now) and named no exit status of a stopped run; the bag tools'
help named neither their 130 / 143 nor the killed writer's folder that ``--overwrite`` now
replaces; the README's memory need left out MC-CNN and the methods that read the right view's
volume, and its list of skipped scenes the ones that do not fit the memory left.
"""

from __future__ import annotations

from pathlib import Path
import re
import signal

import pytest

README = Path(__file__).resolve().parent.parent / 'README.md'


def _readme() -> str:
    return re.sub(r'\s+', ' ', README.read_text(encoding='utf-8'))


def _help(parser: object) -> str:
    return re.sub(r'\s+', ' ', parser.format_help())  # type: ignore[attr-defined]


def _exit_codes(text: str) -> set[int]:
    """The numbers of the help's 'Exit codes: …' sentence."""
    match = re.search(r'Exit codes: ([^.]*)\.', text)
    assert match is not None, text
    return {int(number) for number in re.findall(r'\b\d+\b', match.group(1))}


@pytest.mark.parametrize('signum', [signal.SIGTERM, signal.SIGINT], ids=['SIGTERM', 'SIGINT'])
def test_train_help_names_the_status_a_stopped_run_returns(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
    signum: int,
) -> None:
    from cva_confidence_ros.training import trainer
    from cva_confidence_ros.training.cli import build_parser, main

    def stopped(*_args: object, **_kwargs: object) -> None:
        raise trainer.Stopped(signum, 'step 3 of 4 of epoch 1/2')

    monkeypatch.setattr(trainer, 'train', stopped)
    code = main(['--synthetic', '1', '--no-progress', '--out', str(tmp_path / 'run')])
    assert code == 128 + signum
    err = capsys.readouterr().err
    assert f'stopped by {signal.Signals(signum).name}' in err and '--resume' in err
    text = _help(build_parser())
    assert {0, 1, 2, code} <= _exit_codes(text)
    name = 'SIGTERM' if signum == signal.SIGTERM else 'Ctrl-C'
    assert re.search(rf'{code} (stopped )?by {name}', text), text
    # --resume goes on within an epoch too, not only "after its last finished epoch".
    resume = re.search(r'--resume (continue .*?)--overwrite', text)
    assert resume is not None and 'within an epoch' in resume.group(1)


def test_bag_tools_help_names_their_exit_codes_and_the_killed_writers_folder(
    tmp_path: Path,
) -> None:
    from msg_tools import bag_from_dataset, bag_replay
    from msg_tools.bagio import _STORAGE_MAGIC, check_replaceable
    from msg_tools.progress import GracefulInterrupt

    with GracefulInterrupt() as interrupts:
        signal.raise_signal(signal.SIGTERM)
    sigterm = interrupts.exit_code
    assert sigterm == 143
    for tool in (bag_replay, bag_from_dataset):
        text = _help(tool.build_parser())
        assert _exit_codes(text) == {0, 2, 130, sigterm}, tool.__name__
        assert f'{sigterm} by SIGTERM' in text and '130 interrupted by Ctrl-C' in text
        parser = tool.build_parser()
        overwrite = next(a for a in parser._actions if '--overwrite' in a.option_strings)
        assert 'killed' in (overwrite.help or ''), tool.__name__
        assert 'killed' in (tool.__doc__ or '') and '143' in (tool.__doc__ or '')
    # What the help promises: such a folder (its storage file, no metadata.yaml) is a bag.
    folder = tmp_path / 'bag'
    folder.mkdir()
    (folder / 'bag.mcap').write_bytes(_STORAGE_MAGIC['.mcap'] + b'cut short')
    assert check_replaceable(folder)


def test_readme_memory_need_is_the_pipelines() -> None:
    from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline

    width, height, depth = 2448, 2048, 256
    voxels = width * height * depth

    def need(matcher: str, method: str = 'pkrn', lr_check: bool = False) -> int:
        config = PipelineConfig(
            matcher=matcher, confidence_method=method, max_disparity=depth, lr_check=lr_check,
            device='cpu',
        )
        return StereoPipeline(config).memory_needed(width, height)

    assert need('census_sgm') == 7 * voxels
    assert round(need('census_sgm') / 1e9, 1) == 9.0
    assert need('census_bm') == 4 * voxels
    assert need('census_bm', lr_check=True) == need('census_bm', 'lrd') == 8 * voxels
    assert need('census_bm', 'lrc') == 8 * voxels
    assert need('mccnn_fast') == 4 * voxels + 512 * width * height  # 0.5 KB a pixel, on a CPU
    text = _readme()
    assert (
        '7 bytes a pixel and disparity with census_sgm, 4 with census_bm and mccnn_fast, 4 more '
        "with `lr_check` or a method that reads the right view's volume, lrd and lrc; mccnn_fast "
        'on a CPU 0.5 KB a pixel more for its features: 9.0 GB for 2448×2048 at D = 256 with '
        'census_sgm'
    ) in text


def test_readme_says_a_scene_past_the_memory_left_is_skipped(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import cv2
    import numpy as np

    from cva_confidence_ros.evaluation.cli import main
    import cva_confidence_ros.memory as memory

    rng = np.random.default_rng(0)
    for name in ('small', 'large'):
        scene = tmp_path / 'data' / name
        scene.mkdir(parents=True)
        rows = 10 if name == 'small' else 30
        left = (rng.random((rows, 320)) * 255).astype(np.uint8)
        cv2.imwrite(str(scene / 'left.png'), left)
        cv2.imwrite(str(scene / 'right.png'), np.roll(left, -2, axis=1))
        np.save(scene / 'disparity.npy', np.full((rows, 320), 2, np.float32))
    # The large scene's census_bm volume (30 × 320 × 300 × 4 B = 11.5 MB) past what is "left",
    # the small one's (3.8 MB) within it.
    monkeypatch.setattr(memory, '_CHECKED_FROM', 1_000_000)
    monkeypatch.setattr(memory, 'available_memory', lambda: 5_000_000)
    code = main([
        '--data-root', str(tmp_path / 'data'), '--dataset', 'stereo_folder',
        '--matchers', 'census_bm', '--methods', 'pkrn', '--max-disparity', '300',
        '--json', str(tmp_path / 'eval.json'),
    ])
    err = capsys.readouterr().err
    assert code == 2, err  # the other scene is scored; the run is partial
    assert 'stereo_folder/large skipped' in err and 'memory' in err
    assert 'or whose cost volume needs more memory than is left is logged as skipped' in _readme()
