"""``cva-train``: train CVA-Net on cost volumes of a chosen matcher.

Example (the paper's protocol at D = 64 on the KITTI 2012 pairs plus synthetic data)::

    cva-train --matcher census_bm --max-disparity 64 \\
        --data-root DATA --datasets kitti2012 --synthetic 200 \\
        --val-datasets eth3d --epochs 10 --epochs-low-lr 3 --batch-size 256 --lr 1e-4 \\
        --out out/train_census_bm_d64 --weights-out models/cvanet_census_bm_d64.pt

Multi-GPU: ``torchrun --nproc_per_node=N -m cva_confidence_ros.training.cli --device cuda ...``
(or the ``cva-train`` script under torchrun). Bad input ends with a one-line message and exit
code 2; an interrupted run continues with ``--resume`` from its last checkpoint: the end of an
epoch, or a step within one (``--checkpoint-every N`` steps; and where SIGTERM or Ctrl-C stops
a one-process run, which checkpoints the step it is in first and exits 143 / 130).

A resume must keep what the finished epochs were trained with: data, matcher, D, arch, mode,
sampling, batch size (and number of processes), seed, teacher and warm start, and the learning
rate (and LGC-Net stage) of every finished epoch. It may train longer: ``--epochs`` and
``--epochs-low-lr`` may grow as long as no finished epoch changes its learning rate (raise
``--epochs-low-lr`` once low-rate epochs are finished). The validation scenes must be the
run's too (compared by content: the history compares its epochs on them; a moved
``--val-data-root`` is fine). ``--val-pixels``, device, precision, threads and outputs may change.

Own data with held-out scenes: ``--data-root my/train --datasets stereo_folder
--val-data-root my/val --val-datasets stereo_folder``.

Memory: every scene's cost volume is kept for the whole run (float16, D·(H+12)·(W+12)·2
bytes: all of KITTI 2012 + 2015 at D = 256 is about 98 GB). The start-up log says what they
take before any matching, and a run they do not fit into the available memory is refused
then; ``--volume-cache DIR`` keeps them on disk instead (``--volume-cache`` may change on a
resume).
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator, Sequence
import contextlib
import os
import shlex
import signal
import sys
import traceback

from cva_confidence_ros.errors import ConfigError, CVAError, end_process, from_interrupt
from cva_confidence_ros.training.config import (
    FUSION_SPLITS,
    MODES,
    TRAIN_PRECISIONS,
    TrainConfig,
)

__all__ = ['build_parser', 'config_from_args', 'main']

PROG = 'cva-train'


def _size(text: str) -> tuple[int, int]:
    height, sep, width = text.lower().partition('x')
    try:
        if not sep:
            raise ValueError(text)
        return int(height), int(width)
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected HxW, e.g. 128x256; got {text!r}') from None


def _names(text: str) -> tuple[str, ...]:
    return tuple(dict.fromkeys(item.strip() for item in text.split(',') if item.strip()))


class _DefaultsFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Appends ``(default: X)`` to every option with a value, also to those without help text
    (argparse's formatter skips them), but not where the help names its default itself or
    there is none (None, an empty list): there the help says what happens then."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ''
        if 'default' in text or action.default in (None, (), argparse.SUPPRESS):
            return action.help
        return f'{text} (default: %(default)s)'.lstrip()


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``cva-train``."""
    defaults = TrainConfig.__dataclass_fields__
    parser = argparse.ArgumentParser(
        prog=PROG,
        description='Train CVA-Net (confidence from cost volumes) for one matcher and depth D.',
        epilog='Exit codes: 0 done, 2 bad input (one line on stderr), 1 failed (under torchrun '
        'also a process that lost another of its group: --resume goes on), 130 stopped by '
        'Ctrl-C, 143 by SIGTERM (a Slurm preemption); --resume goes on from the checkpoint '
        'the message names.',
        formatter_class=_DefaultsFormatter,
    )
    data = parser.add_argument_group('data')
    data.add_argument(
        '--arch',
        default=defaults['arch'].default,
        help='network architecture to train: cvanet (the paper network), cvanet_lite, '
        "cvanet_fast (this project's light and CPU networks) or the baselines ccnn, lfn, "
        'lgcnet (disparity + image; --mode sparse = 9×9 patches)',
    )
    data.add_argument('--matcher', default=defaults['matcher'].default, help='matcher name')
    data.add_argument(
        '--max-disparity',
        type=int,
        default=defaults['max_disparity'].default,
        help='cost-volume depth D; images are halved until the ground truth fits',
    )
    data.add_argument('--data-root', default=None, help='folder holding the data sets')
    data.add_argument(
        '--datasets',
        type=_names,
        default=(),
        help="training data sets, comma-separated, each 'name' or 'name:split'; "
        "stereo_folder reads your own pairs (<scene>/left.png, right.png, "
        'disparity.pfm|npy|png)',
    )
    data.add_argument(
        '--max-scenes', type=int, default=None, help='at most N scenes per data set (default: all)'
    )
    data.add_argument('--synthetic', type=int, default=0, help='synthetic training pairs')
    data.add_argument(
        '--synthetic-size',
        type=_size,
        default=None,
        help='HxW of synthetic pairs (default: max(128, D) x max(256, 2D))',
    )
    data.add_argument('--synthetic-seed', type=int, default=0, help='seed of the first pair')
    data.add_argument(
        '--val-datasets',
        type=_names,
        default=(),
        help="held-apart validation data sets, comma-separated, each 'name' or 'name:split' "
        '(read from --val-data-root if given, else --data-root)',
    )
    data.add_argument(
        '--val-data-root',
        default=None,
        help='folder holding the validation data sets (default: --data-root); e.g. your own '
        'held-out stereo_folder scenes: --val-data-root my/val --val-datasets stereo_folder; '
        'refused where its scenes are the training pairs (same images and ground truth)',
    )
    data.add_argument('--val-synthetic', type=int, default=0, help='synthetic validation pairs')
    data.add_argument(
        '--val-pixels',
        type=int,
        default=defaults['val_pixels'].default,
        help='fixed pixel subset for the validation AUC',
    )
    run = parser.add_argument_group('procedure')
    run.add_argument('--mode', choices=MODES, default='sparse', help='sample extracts or crops')
    run.add_argument(
        '--crop-size',
        type=int,
        default=defaults['crop_size'].default,
        help='dense mode: outputs per crop side',
    )
    run.add_argument(
        '--vflip',
        action='store_true',
        help='turn half of the training samples upside down (augmentation, not in the paper)',
    )
    run.add_argument(
        '--epochs', type=int, default=defaults['epochs'].default, help='epochs at --lr'
    )
    run.add_argument(
        '--epochs-low-lr',
        type=int,
        default=defaults['epochs_low_lr'].default,
        help='further epochs at --lr × --low-lr-factor',
    )
    run.add_argument(
        '--batch-size',
        type=int,
        default=defaults['batch_size'].default,
        help='samples per step (dense mode: ceil(batch / crop²) crops)',
    )
    run.add_argument(
        '--lr', type=float, default=defaults['lr'].default, help='learning rate of Adam'
    )
    run.add_argument(
        '--low-lr-factor',
        type=float,
        default=defaults['low_lr_factor'].default,
        help='learning-rate factor of the last epochs',
    )
    run.add_argument(
        '--samples-per-epoch',
        type=int,
        default=None,
        help='labelled samples per epoch (default: as many as there are labelled pixels: '
        'sparse mode uses each once, dense mode places crops at random and may use a pixel '
        'more than once and another not at all)',
    )
    run.add_argument(
        '--teacher',
        default=None,
        help='weights of a trained network to distil from (e.g. models/cvanet_<matcher>_d<D>.pt)',
    )
    run.add_argument(
        '--distill-weight',
        type=float,
        default=defaults['distill_weight'].default,
        help='A: loss = (1-A)*BCE(label) + A*BCE(teacher probability), labelled pixels',
    )
    run.add_argument(
        '--init-weights',
        default=None,
        help='start from these weights (same --arch; of another D, the first fully-connected '
        'layer is transferred on the shared disparities, zeros beyond)',
    )
    run.add_argument(
        '--fusion-split',
        choices=FUSION_SPLITS,
        default=defaults['fusion_split'].default,
        help='lgcnet: alternate = parts on half of the scenes (sorted by name, even positions), '
        'fusion on the other half; none = both stages on all scenes',
    )
    run.add_argument(
        '--seed', type=int, default=0, help='seed of initialisation, sampling and dropout'
    )
    run.add_argument('--device', default='cpu', help="'cpu', 'cuda', 'cuda:N' or 'auto'")
    run.add_argument(
        '--precision',
        choices=TRAIN_PRECISIONS,
        default='fp32',
        help='bf16: mixed precision (bfloat16 autocast, float32 weights); for CUDA GPUs',
    )
    run.add_argument(
        '--threads', type=int, default=None, help="torch and numba CPU threads (default: torch's)"
    )
    run.add_argument(
        '--volume-cache',
        metavar='DIR',
        default=None,
        help='keep the cost volumes in files in DIR, mapped into memory, instead of all in '
        'memory (default; D·(H+12)·(W+12)·2 bytes a scene: 248 MB for a 1242×375 KITTI pair '
        'at D = 256): for data that do not fit in memory (the start-up log says what they '
        'take; a run they clearly do not fit is refused before matching). Written once per '
        'scene, reused by the epochs, a --resume and later runs on the same pairs, matcher '
        'and D (a run whose volumes still to write exceed the free disk there is refused '
        'before matching); the results are those of the in-memory run. Delete DIR to free '
        'the disk',
    )
    output = parser.add_argument_group('output')
    output.add_argument(
        '--out',
        default=defaults['out'].default,
        help='checkpoints and log (refused while another cva-train run trains there)',
    )
    output.add_argument(
        '--checkpoint-every',
        type=int,
        metavar='N',
        default=0,
        help='also checkpoint every N training steps within an epoch (default: 0, at the end '
        'of each epoch only), for long epochs: a --resume goes on from the last such step, to '
        'the bit as if the run had not stopped. A one-process run of these networks stopped '
        'by SIGTERM or Ctrl-C checkpoints the step it is in anyway (exit 143 / 130); under '
        'torchrun the processes stop at once, and --resume goes on from the last checkpoint',
    )
    output.add_argument(
        '--weights-out', default=None, help='final weights PATH.pt (+ PATH.md, PATH.json)'
    )
    # A resume continues the run in OUT, an overwrite starts it afresh: one of them.
    restart = output.add_mutually_exclusive_group()
    restart.add_argument(
        '--resume',
        action='store_true',
        help='continue from OUT/checkpoint.pt: after its last finished epoch, or within an '
        'epoch at the step a --checkpoint-every checkpoint or a stop by SIGTERM / Ctrl-C '
        'saved; refused unless the '
        'data (validation scenes included), matcher, D, arch, mode, sampling, batch size, '
        'processes, seed, teacher and warm start are those of the run and every finished '
        'epoch keeps its learning rate; '
        '--epochs / --epochs-low-lr may grow to train longer',
    )
    restart.add_argument(
        '--overwrite',
        action='store_true',
        help='start afresh in an OUT that holds the checkpoint of an earlier run (its '
        'checkpoint and history.json are removed first), and let --weights-out replace '
        'existing weights and their card',
    )
    output.add_argument(
        '--no-progress',
        action='store_true',
        help='no progress bar (there is none either where stderr is no terminal: a log file, '
        'a pipe)',
    )
    return parser


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    """Translate parsed arguments into a validated :class:`TrainConfig`."""
    return TrainConfig(
        arch=args.arch,
        matcher=args.matcher,
        max_disparity=args.max_disparity,
        data_root=args.data_root,
        datasets=args.datasets,
        max_scenes=args.max_scenes,
        synthetic=args.synthetic,
        synthetic_size=args.synthetic_size,
        synthetic_seed=args.synthetic_seed,
        val_datasets=args.val_datasets,
        val_data_root=args.val_data_root,
        val_synthetic=args.val_synthetic,
        val_pixels=args.val_pixels,
        mode=args.mode,
        crop_size=args.crop_size,
        vflip=args.vflip,
        epochs=args.epochs,
        epochs_low_lr=args.epochs_low_lr,
        batch_size=args.batch_size,
        lr=args.lr,
        low_lr_factor=args.low_lr_factor,
        samples_per_epoch=args.samples_per_epoch,
        seed=args.seed,
        device=args.device,
        precision=args.precision,
        threads=args.threads,
        out=args.out,
        weights_out=args.weights_out,
        resume=args.resume,
        overwrite=args.overwrite,
        # A bar on a log file or a pipe is a stream of carriage returns (CI logs, `| tee`).
        progress=not args.no_progress and _is_terminal(sys.stderr),
        teacher=args.teacher,
        distill_weight=args.distill_weight,
        init_weights=args.init_weights,
        fusion_split=args.fusion_split,
        volume_cache=args.volume_cache,
        checkpoint_every=args.checkpoint_every,
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``cva-train``; returns the exit code (0 = done, 2 = bad input, 1 = failed: under
    torchrun also a process that lost another of its group, said in one line; 130 / 143 =
    stopped by Ctrl-C / SIGTERM, said in one line with what the checkpoint holds).

    Under torchrun a run that failed ends its process here, with the code: its process group
    is left as it was (see ``_Dist.settle``), and finalising the interpreter under gloo's
    threads could turn the error's exit into a SIGABRT.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    from cva_confidence_ros.memory import keep_freed_memory

    keep_freed_memory()
    try:
        code = _train(args, argv)
    except Exception as exc:
        if not _group_left():
            raise
        lost = _lost_process(exc)
        if lost:
            # Exit 1, not 2 (bad input): the run is fine and goes on with --resume.
            print(f'{PROG}: error: {lost}; --resume goes on from the last checkpoint in '
                  f'{args.out} (the work since it is lost)', file=sys.stderr)
        else:
            traceback.print_exc()
        code = 1
    if _group_left():
        end_process(code)
    return code


def _train(args: argparse.Namespace, argv: list[str]) -> int:
    try:
        config = config_from_args(args)
        from cva_confidence_ros.training.trainer import stop_on_signals, train

        with _hold_out(config), stop_on_signals():
            train(config, command=shlex.join([PROG, *argv]))
    except CVAError as exc:
        print(f'{PROG}: error: {exc}', file=sys.stderr)
        return 2
    except (KeyboardInterrupt, SystemError) as exc:
        # A Ctrl-C in a numba kernel (the cost volumes) surfaces as a SystemError.
        if not from_interrupt(exc):
            raise
        signum, saved = _stopped(exc)
        if saved:
            where = f'the checkpoint in {args.out} holds {saved}: --resume goes on from there'
        elif _has_checkpoint(args.out):
            where = (f'--resume goes on from the last checkpoint in {args.out} (the work '
                     'since it is lost)')
        else:
            # Stopped while the scenes were prepared, say: a resume has nothing to go on from.
            where = f'no checkpoint was written in {args.out} yet: run it again from the start'
        print(f'{PROG}: stopped by {signal.Signals(signum).name}; {where}', file=sys.stderr)
        return 128 + signum
    return 0


def _has_checkpoint(out: str) -> bool:
    from pathlib import Path

    from cva_confidence_ros.training.trainer import CHECKPOINT_NAME

    return (Path(out) / CHECKPOINT_NAME).is_file()


def _stopped(exc: BaseException) -> tuple[int, str]:
    """(signal, what the checkpoint holds) of the trainer's ``Stopped`` in ``exc`` or its
    causes (a numba kernel's SystemError); (SIGINT, '') for a plain Ctrl-C."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        signum = getattr(current, 'signum', None)
        if isinstance(current, KeyboardInterrupt) and isinstance(signum, int):
            return signum, str(getattr(current, 'saved', ''))
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return int(signal.SIGINT), ''


def _is_terminal(stream: object) -> bool:
    isatty = getattr(stream, 'isatty', None)
    try:
        return bool(isatty and isatty())
    except (OSError, ValueError):  # a closed stream
        return False


@contextlib.contextmanager
def _hold_out(config: TrainConfig) -> Iterator[None]:
    """Hold ``config.out`` for this run (an exclusive lock on the folder, released when the
    process ends): a second run into the same ``--out`` is refused at its start.

    Two at once both trained there, their checkpoints and history replacing each other's
    epoch by epoch (a later ``--resume`` took one run's checkpoint with the other's history),
    until one failed on the other's temporary file. Only process 0 of a torchrun group holds
    it (the others write nothing there); where the file system has no locks, nothing is held.

    Raises:
        ConfigError: Another process holds ``config.out``, or it cannot be made.
    """
    if os.environ.get('RANK', '0') != '0':
        yield
        return
    from cva_confidence_ros.outputs import check_output_dir, check_output_file, lock_folder
    from cva_confidence_ros.training.trainer import check_run_options

    check_run_options(config)  # refused before --out is made, as the trainer refuses them
    if config.weights_out:  # refused before --out is made, as the trainer refuses it
        check_output_file(config.weights_out, '--weights-out')
    out = check_output_dir(config.out, '--out')
    try:
        handle = lock_folder(out)  # None: nothing to hold (the trainer says what is wrong)
    except BlockingIOError:
        raise ConfigError(
            f'--out {config.out} is in use by another cva-train run (still going); wait '
            'for it to end or give another --out'
        ) from None
    try:
        yield
    finally:
        if handle is not None:
            os.close(handle)


#: What gloo and NCCL raise on a process whose peer in the group is gone (killed, out of
#: memory, its node down): a traceback ending in 'Connection reset by peer' told no cause.
_LOST_PEER = (
    'Connection reset by peer', 'Connection closed by peer', 'Broken pipe',
    'NCCL communicator was aborted', 'remote process exited',
)


def _lost_process(exc: BaseException) -> str:
    """Why a torchrun process failed, where ``exc`` (or an error it came from) says that
    another process of the group is gone; '' otherwise."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        if isinstance(current, RuntimeError):  # torch's DistBackendError is one
            said = str(current)
            found = next((words for words in _LOST_PEER if words in said), None)
            if found is not None:
                rank = os.environ.get('RANK', '?')
                world = os.environ.get('WORLD_SIZE', '?')
                return (f'process {rank} of {world} lost another process of its torchrun '
                        f'group ({found}): it was killed or ended (out of memory, its node '
                        "down, an error in its own output); torchrun's summary names it")
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return ''


def _group_left() -> bool:
    """Whether a torchrun process group outlived the run (it ends with a finished one)."""
    distributed = sys.modules.get('torch.distributed')
    return distributed is not None and distributed.is_available() and distributed.is_initialized()


if __name__ == '__main__':
    sys.exit(main())
