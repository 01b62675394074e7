"""``cva-demo`` / ``make demo``: the main job end to end on an embedded default.

The Middlebury 2014 Motorcycle pair that scikit-image ships is

1. matched with every registered matcher (disparity PNGs and a cost-volume summary);
2. written to a rosbag2 (MCAP) as a robot would record it (``cva-bag-from-dataset``);
3. replayed through the node's pipeline with the shipped CVA-Net weights and the hand-crafted
   measures (``cva-bag-replay``), which writes an output bag, a report and PNGs;

and the AUC table is printed. Runs in about a minute on a 2-core CPU (set-up done): the images
are processed at quarter resolution (``--downsample 4``), which keeps CVA-Net to about 16 s a
matcher.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import sys
import time

import numpy as np

from cva_confidence_ros import strict_json
from cva_confidence_ros.errors import (
    ConfigError,
    CVAError,
    DataError,
    closed_stdout,
    from_interrupt,
    reason,
    sigterm_as_interrupt,
    stdout_closed,
)
from cva_confidence_ros.outputs import check_output_dir

__all__ = ['main']

_SUMMARY_KEYS = (
    'error_rate', 'auc', 'auc_opt', 'kept_density', 'kept_error_rate', 'expected_kept_error',
    'kept_epe',
)


def _log(message: str) -> None:
    print(f'[demo] {message}', file=sys.stderr, flush=True)


def _write_png(path: Path, image: np.ndarray) -> None:
    """``cv2.imwrite``, which only returns False (a full disk, a folder in the way).

    Raises:
        DataError: The file cannot be written.
    """
    import cv2

    if not cv2.imwrite(str(path), image):
        raise DataError(f'cannot write {path} (a full disk, or no permission?)')


def _match_all(
    out: Path, matchers: list[str], max_disparity: int, downsample: int
) -> list[dict[str, object]]:
    """Run the matchers on the Motorcycle pair; write disparity PNGs; return a summary.

    Raises:
        CVAError: A depth the pair cannot be matched at, or an output that cannot be written
            (:class:`DataError`).
    """
    import cv2

    from cva_confidence_ros.datasets import fit_disparity_range, load_scene, resize_sample
    from cva_confidence_ros.matching import compute_cost_volume, wta_disparity
    from cva_confidence_ros.metrics import kitti_error

    sample = load_scene('motorcycle', None, 'motorcycle')
    if downsample > 1:
        sample = resize_sample(sample, downsample)
    sample, factor = fit_disparity_range(sample, max_disparity)
    if factor > 1:  # step 1 then runs at another size than the replay of step 3
        height, width = sample.left.shape[:2]
        _log(f'the ground truth does not fit into D = {max_disparity} at 1/{downsample} size: '
             f'matching at 1/{downsample * factor} ({width}×{height} px) instead')
    rows = []
    for name in matchers:
        tic = time.perf_counter()
        volume = compute_cost_volume(sample.left, sample.right, name, max_disparity)
        seconds = time.perf_counter() - tic
        disparity = wta_disparity(volume)
        known = np.isfinite(sample.disparity)
        wrong = kitti_error(disparity, sample.disparity)[known]
        png = out / f'disparity_{name}.png'
        scaled = np.clip(disparity * (255.0 / max(max_disparity - 1, 1)), 0, 255)
        _write_png(png, cv2.applyColorMap(scaled.astype(np.uint8), cv2.COLORMAP_TURBO))
        rows.append(
            {
                'matcher': name,
                'shape': list(volume.shape),
                'cost_min': float(volume.min()),
                'cost_mean': float(volume.mean()),
                'cost_max': float(volume.max()),
                'seconds': round(seconds, 3),
                'error_rate': float(wrong.mean()),
                'png': png.name,  # beside the summary (the run's folder may move)
            }
        )
        _log(f'{name}: cost volume {volume.shape} in {seconds:.2f} s, '
             f'WTA error rate {wrong.mean():.3f} -> {png}')
    _write_png(out / 'left.png', cv2.cvtColor(sample.left, cv2.COLOR_RGB2BGR))
    summary = out / 'cost_volume_summary.json'
    try:
        summary.write_text(strict_json.dumps(rows, indent=2) + '\n')
    except OSError as exc:
        raise DataError(f'cannot write {summary}: {reason(exc)}') from None
    return rows


def _check_args(args: argparse.Namespace) -> tuple[list[str], list[str]]:
    """Everything the three steps need, checked before the first: (matchers, methods)."""
    from cva_confidence_ros.confidence import CONFIDENCE_METHODS
    from cva_confidence_ros.matching import MATCHERS

    if args.downsample not in (1, 2, 4):
        raise ConfigError(f'--downsample must be 1, 2 or 4; got {args.downsample}')
    if not 1 <= args.max_disparity <= 1024:
        raise ConfigError(f'--max-disparity must be in [1, 1024]; got {args.max_disparity}')
    # dict.fromkeys: a name given twice is run once (not twice, in twice the time)
    matchers = list(dict.fromkeys(n.strip() for n in args.matchers.split(',') if n.strip()))
    methods = list(dict.fromkeys(n.strip() for n in args.methods.split(',') if n.strip()))
    if not matchers or not methods:
        raise ConfigError('--matchers and --methods must each name at least one')
    for name in matchers:
        MATCHERS.get(name)
    for name in methods:
        CONFIDENCE_METHODS.get(name)
    _check_weights(matchers, methods, args.max_disparity)
    args.out = check_output_dir(args.out, '--out')  # a str: Path('') would be '.'
    _check_in_the_way(args.out, matchers, methods)
    return matchers, methods


def _check_in_the_way(out: Path, matchers: list[str], methods: list[str]) -> None:
    """Refuse, before step 1, what stands where the demo writes under ``--out``: a file or a
    link where it replaces a folder (steps 2 and 3 delete and remake theirs), a folder where
    it writes a file.

    Raises:
        ConfigError: The first such path, named.
    """
    replaced = [out / 'motorcycle_bag'] + [
        out / 'replay' / f'{matcher}__{method}' for matcher in matchers for method in methods
    ]
    for folder in replaced:
        if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
            kind = 'a link' if folder.is_symlink() else 'a file'
            raise ConfigError(
                f'--out {out}: {folder} is {kind}, where the demo writes a folder of its '
                f'outputs (deleting an older one); move it away or pick another --out'
            )
    replay = out / 'replay'
    if replay.exists() and not replay.is_dir():
        raise ConfigError(f'--out {out}: {replay} is a file, where the demo writes a folder')
    files = [out / f'disparity_{matcher}.png' for matcher in matchers]
    for path in (*files, out / 'left.png', out / 'cost_volume_summary.json'):
        if path.is_dir():
            raise ConfigError(f'--out {out}: {path} is a folder, where the demo writes a file')


def _check_weights(matchers: list[str], methods: list[str], max_disparity: int) -> None:
    """Refuse a learned method without shipped weights for a matcher at this depth (e.g.
    ``--max-disparity 32``) before step 1, rather than in step 3 after the others ran.

    Raises:
        ModelError: The first missing weights file, with how to train it.
    """
    from cva_confidence_ros.confidence import CONFIDENCE_METHODS
    from cva_confidence_ros.model import default_weights_path

    for method in methods:
        arch = getattr(CONFIDENCE_METHODS.get(method), 'arch', None)
        if not isinstance(arch, str) or not arch:
            continue  # a hand-crafted measure: no weights
        for matcher in matchers:
            default_weights_path(matcher, max_disparity, arch)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``cva-demo``."""
    from cva_confidence_ros.memory import keep_freed_memory

    keep_freed_memory()
    parser = argparse.ArgumentParser(
        prog='cva-demo', description=__doc__.split('\n\n')[0],
        epilog='Exit codes: 0 done, 2 bad input or a step that failed (one line on stderr), '
        '130 stopped by Ctrl-C, 143 by SIGTERM.')
    parser.add_argument('--out', default='out/demo', help='output folder (default: %(default)s)')
    parser.add_argument(
        '--downsample', type=int, default=4,
        help='processing downsample (4 keeps CVA-Net on a 2-core CPU to about 16 s a matcher)'
    )
    parser.add_argument('--max-disparity', type=int, default=64, help='cost-volume depth')
    parser.add_argument(
        '--matchers', default='census_bm,census_sgm,mccnn_fast', help='comma-separated matchers'
    )
    parser.add_argument(
        '--methods',
        default='cva_net,cva_net_lite,cva_net_fast,ccnn,lfn,lgc_net,pkrn,mlm,lrd,lrc,score',
        help='confidence methods to replay',
    )
    args = parser.parse_args(argv)
    try:
        matchers, methods = _check_args(args)
    except CVAError as err:
        parser.error(str(err))

    # SIGTERM (a CI job's time limit) ended step 1 without a word: it is a Ctrl-C here (exit
    # 143); steps 2 and 3 (the bag tools) answer both signals with 130 / 143 themselves.
    step = [1]
    with sigterm_as_interrupt() as terminated:
        try:
            return _run(args, matchers, methods, step)
        except BrokenPipeError:
            if not stdout_closed():
                raise
            return closed_stdout()
        except (KeyboardInterrupt, SystemError) as exc:
            if not from_interrupt(exc):
                raise
            how = 'stopped by SIGTERM' if terminated else 'interrupted'
            print(f'cva-demo: {how} in step {step[0]}', file=sys.stderr)
            return 143 if terminated else 130


def _run(args: argparse.Namespace, matchers: list[str], methods: list[str],
         step: list[int]) -> int:
    """Steps 1 to 3 of :func:`main`; ``step[0]`` says which one is under way."""
    from msg_tools import bag_from_dataset, bag_replay

    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    _log(f'step 1/3: matching the scikit-image Motorcycle pair at 1/{args.downsample} size')
    try:
        _match_all(out, matchers, args.max_disparity, args.downsample)
    except CVAError as err:  # e.g. a depth too wide for the pair at this size
        print(f'cva-demo: error: {err}', file=sys.stderr)
        return 2

    step[0] = 2
    bag = out / 'motorcycle_bag'
    _log(f'step 2/3: writing the pair as a rosbag2 (MCAP) to {bag}')
    if bag.exists():
        import shutil

        shutil.rmtree(bag)
    code = bag_from_dataset.main(['--dataset', 'motorcycle', '--out', str(bag)])
    if code:
        return code

    step[0] = 3
    _log('step 3/3: replaying the bag through the pipeline (matcher x confidence method)')
    table: list[tuple[str, str, dict[str, float]]] = []
    for matcher in matchers:
        for method in methods:
            name = f'{matcher}__{method}'
            replay_out = out / 'replay' / name
            if replay_out.exists():
                import shutil

                shutil.rmtree(replay_out)
            code = bag_replay.main([
                str(bag), '--out', str(replay_out / 'bag'), '--report', str(replay_out),
                '--matcher', matcher, '--confidence-method', method,
                '--max-disparity', str(args.max_disparity),
                '--downsample', str(args.downsample),
            ])
            if code:
                return code
            report = json.loads((replay_out / 'report.json').read_text())
            table.append((matcher, method, report['summary']))

    print()
    print(f'AUC x 100 on the Middlebury 2014 Motorcycle pair (scikit-image), '
          f'1/{args.downsample} resolution, D = {args.max_disparity}, all ground-truth pixels')
    print()
    # expected kept error: what the confidence itself predicts for the kept pixels (networks
    # only, whose output is a probability), next to what the ground truth says; kept EPE: their
    # mean |d − d_gt| in pixels (sub-pixel disparities)
    print('| matcher | method | error rate % | AUC | AUC opt | kept density % | kept error % '
          '| expected kept error % | kept EPE px |')
    print('|---|---|---|---|---|---|---|---|---|')
    for matcher, method, summary in table:
        values = [summary.get(key) for key in _SUMMARY_KEYS]
        cells = [
            '–' if v is None
            else f'{v:.3f}' if key == 'kept_epe'
            else f'{100 * v:.{1 if key == "kept_density" else 2}f}'
            for key, v in zip(_SUMMARY_KEYS, values, strict=True)
        ]
        print(f'| {matcher} | {method} | ' + ' | '.join(cells) + ' |')
    print()
    print(f'outputs: {out.resolve()} (disparity_*.png, cost_volume_summary.json, '
          f'motorcycle_bag/, replay/<matcher>__<method>/{{bag,report.json,*.png}})')
    print(f'done in {time.perf_counter() - start:.0f} s')
    return 0


if __name__ == '__main__':
    sys.exit(main())
