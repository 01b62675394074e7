"""Model cards: the facts of a training run, beside the weights, as Markdown and JSON."""

from __future__ import annotations

from collections.abc import Mapping
import os
from pathlib import Path
import platform
from typing import Any

import numpy as np
import torch

from cva_confidence_ros import strict_json
from cva_confidence_ros.outputs import write_text_atomic

__all__ = ['card_paths', 'hardware_facts', 'write_model_card']


def card_paths(weights_path: str | os.PathLike[str]) -> tuple[Path, Path]:
    """(``PATH.md``, ``PATH.json``) for weights ``PATH.pt``."""
    path = Path(weights_path)
    return path.with_suffix('.md'), path.with_suffix('.json')


def _cpu_model() -> str:
    try:
        with open('/proc/cpuinfo', encoding='utf-8') as handle:
            for line in handle:
                if line.startswith('model name'):
                    return line.split(':', 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def hardware_facts(device: torch.device, world_size: int = 1) -> dict[str, Any]:
    """CPU model, cores, torch threads, GPU name (if used), processes, torch version."""
    facts: dict[str, Any] = {
        'cpu': _cpu_model(),
        'cpu_cores': os.cpu_count(),
        'torch_threads': torch.get_num_threads(),
        'device': str(device),
        'gpu': torch.cuda.get_device_name(device) if device.type == 'cuda' else None,
        'processes': world_size,
        'torch': str(torch.__version__),
        'python': platform.python_version(),
    }
    return facts


def _fmt(value: Any, digits: int = 4) -> str:
    """A fact for the card: ``digits`` significant digits of a measured float; 12 for a
    setting (``--lr 0.00012345`` is 0.00012345, not 0.0001234; lr × 0.1 shows no float
    noise)."""
    if value is None:
        return '—'
    if isinstance(value, (float, np.floating)):
        return f'{float(value):.{digits}g}'
    if isinstance(value, (list, tuple)):
        return ', '.join(_fmt(v, digits) for v in value) or '—'
    return str(value)


def _code(text: Any) -> str:
    """``text`` as a Markdown code span: a backtick in it (``--out 'a`b'``) ended a span in
    single backticks, so the fence is one backtick longer than the longest run inside."""
    if text is None or text == '':
        return '—'  # '``' is no code span: it showed as two backticks; 'None' as a command
    text = str(text)
    longest = run = 0
    for char in text:
        run = run + 1 if char == '`' else 0
        longest = max(longest, run)
    fence = '`' * (longest + 1)
    pad = ' ' if text.startswith('`') or text.endswith('`') else ''
    return f'{fence}{pad}{text}{pad}{fence}'


_CVANET_TEXT = (
    'CVA-Net',
    'CVA-Net (Mehltretter & Heipke, ICCVW 2019): per-pixel confidence of the winner-takes-all '
    'disparity, learned from 13×13×D extracts of the normalised cost volume.',
)
#: arch → (title, one-paragraph description) of the card.
_ARCH_TEXT = {
    'cvanet': _CVANET_TEXT,
    'cvanet_lite': (
        'CVA-Net-Lite',
        'CVA-Net-Lite (`model/lite.py`): a light network with the input and output of CVA-Net '
        '(13×13×D extracts of the normalised cost volume → confidence of the winner-takes-all '
        'disparity), the same three stages with about 54× fewer multiply-adds; trained on the '
        'labels, optionally distilled from CVA-Net (see the loss line).',
    ),
    'cvanet_fast': (
        'CVA-Net-Fast',
        'CVA-Net-Fast (`model/fast.py`): a network for CPUs with the input and output of CVA-Net '
        '(13×13×D extracts of the normalised cost volume → confidence of the winner-takes-all '
        'disparity): per pixel the 9 costs around the WTA minimum and d_WTA / D through two '
        'fully-connected layers, then six 3×3 convolutions over the 13×13 window in the image '
        'plane; about 590× fewer multiply-adds than CVA-Net at D = 64.',
    ),
}


def _share(value: Any) -> str:
    """A fraction in [0, 1] as a percentage, '—' if unknown."""
    return '—' if value is None else f'{100 * float(value):.1f} %'


def _loss_line(facts: Mapping[str, Any]) -> str:
    optimiser = 'optimiser: Adam (β1 0.9, β2 0.999); dropout 0.5'
    weight = facts.get('distill_weight') or 0.0
    if not facts.get('teacher') or not weight:
        return f'- loss: binary cross-entropy; {optimiser}'
    teacher = facts.get('teacher_meta') or {}
    return (
        f'- loss: (1 − A)·BCE(label) + A·BCE(teacher probability) on labelled pixels, '
        f'A = {_fmt(weight, 12)}; teacher {_code(Path(str(facts["teacher"])).name)} '
        f'(arch {teacher.get("arch")}, matcher {teacher.get("matcher")}, '
        f'{_fmt(teacher.get("samples_seen"))} training samples); {optimiser}'
    )


def _crop_side(facts: Mapping[str, Any]) -> int | None:
    """The side of the dense-mode crops: ``crop_size``, or the smallest training scene side if
    that is smaller (the crops of ``training.data.dense_crops``)."""
    side = facts.get('crop_size')
    sides = [min(int(s['height']), int(s['width'])) for s in facts.get('scenes', [])]
    return min([int(side), *sides]) if side is not None else None


def _init_lines(facts: Mapping[str, Any]) -> list[str]:
    if not facts.get('init_weights'):
        return []
    source = facts.get('init_meta') or {}
    return [
        f'- initialised from {_code(Path(str(facts["init_weights"])).name)} '
        f'({_fmt(source.get("samples_seen"))} training samples)'
    ]


def write_model_card(
    weights_path: str | os.PathLike[str], facts: Mapping[str, Any]
) -> tuple[Path, Path]:
    """Write ``PATH.md`` and ``PATH.json`` describing the weights ``PATH.pt``.

    Args:
        weights_path: The weights file the card belongs to.
        facts: The training summary (see :func:`cva_confidence_ros.training.train`): matcher,
            max_disparity, data sets and scenes, samples, epochs, batch size, learning rates,
            hardware, wall time, command line, final loss and validation AUC, history.

    Returns:
        The two written paths.

    Raises:
        DataError: A file cannot be written (an older one there is left as it was).
    """
    md_path, json_path = card_paths(weights_path)
    # A NaN or infinite number (a diverged loss) is null in the JSON, 'nan' / 'inf' in the text.
    json_text = strict_json.dumps(dict(facts), indent=2, sort_keys=True)
    hardware = facts.get('hardware', {})
    title, about = _ARCH_TEXT.get(str(facts.get('arch', 'cvanet')), _ARCH_TEXT['cvanet'])
    lines = [
        f'# {facts.get("network") or title} weights {_code(Path(weights_path).name)}',
        '',
        facts.get('network_description') or about,
        '',
        '## Use',
        '',
        f'- matcher: {_code(facts.get("matcher"))}',
        f'- cost-volume depth D: {_fmt(facts.get("max_disparity"))} (training and evaluation '
        'images were halved until their ground truth fit D; on the node choose `max_disparity` '
        'and `downsample` so that your disparities stay below D)',
        '',
        '## Training data',
        '',
        f'- data sets: {_fmt(facts.get("datasets"))}',
        f'- synthetic pairs: {_fmt(facts.get("synthetic"))}',
        f'- training scenes ({len(facts.get("scenes", []))}): '
        f'{_fmt([s["name"] for s in facts.get("scenes", [])])}',
        f'- labelled pixels: {_fmt(facts.get("labelled_pixels"))}, '
        f'wrong-label fraction: {_fmt(facts.get("fraction_wrong"))}',
        f'- validation scenes: {_fmt([s["name"] for s in facts.get("val_scenes", [])])} '
        f'({_fmt(facts.get("val_pixels"))} pixels)'
        # Held-out scenes of your own share the training names (stereo_folder/scene0): the
        # folder tells them apart.
        + (f'; data sets read from --val-data-root {_code(facts["val_data_root"])}'
           if facts.get('val_data_root') else ''),
        '',
        '## Procedure',
        '',
        f'- mode: {_fmt(facts.get("mode"))}'
        + (f' (crops of {_crop_side(facts)}² outputs)' if facts.get('mode') == 'dense' else '')
        + ('; half of them turned upside down (--vflip)' if facts.get('vflip') else ''),
        f'- epochs: {_fmt(facts.get("epochs"))} at lr {_fmt(facts.get("lr"), 12)} + '
        f'{_fmt(facts.get("epochs_low_lr"))} at lr {_fmt(facts.get("lr_low"), 12)}',
        f'- batch size: {_fmt(facts.get("batch_size"))}, samples per epoch: '
        # Dense crops are whole: an epoch ends with the crop that reaches the count.
        + ('at least ' if facts.get('mode') == 'dense' else '')
        + f'{_fmt(facts.get("samples_per_epoch"))}, samples seen: '
        f'{_fmt(facts.get("samples_seen"))}'
        + (', arithmetic: bf16 autocast' if facts.get('precision') == 'bf16' else ''),
        *(
            [f'- {note}' for note in facts['network_notes']]
            if facts.get('network_notes')
            else [_loss_line(facts), *_init_lines(facts)]
        ),
        f'- seed: {_fmt(facts.get("seed"))}',
        '',
        '## Hardware and time',
        '',
        f'- CPU: {_fmt(hardware.get("cpu"))} ({_fmt(hardware.get("cpu_cores"))} cores, '
        f'{_fmt(hardware.get("torch_threads"))} torch threads)',
        f'- GPU: {_fmt(hardware.get("gpu"))}; processes: {_fmt(hardware.get("processes"))}',
        f'- wall time: {_fmt(facts.get("wall_time_s"))} s',
        f'- command: {_code(facts.get("command"))}',
        '',
        '## Results',
        '',
        f'- final train loss: {_fmt(facts.get("final_train_loss"))}',
        f'- validation AUC: {_fmt(facts.get("final_val_auc"))} '
        f'(optimal {_fmt(facts.get("final_val_auc_opt"))}, error rate '
        f'{_fmt(facts.get("final_val_error_rate"))}; '
        f'{_share(facts.get("final_val_high"))} of the outputs ≥ 0.5)',
        '',
        '| epoch | lr | train loss | samples/s | val AUC |',
        '|---|---|---|---|---|',
    ]
    for record in facts.get('history', []):
        lines.append(
            f'| {record["epoch"]} | {_fmt(record["lr"], 12)} | {_fmt(record["train_loss"])} | '
            f'{_fmt(record["samples_per_s"])} | {_fmt(record.get("val_auc"))} |'
        )
    lines += ['', '## Evaluation on the develop split', '', '(to be added)', '']
    write_text_atomic(json_path, json_text + '\n', 'model card ')
    write_text_atomic(md_path, '\n'.join(lines), 'model card ')
    return md_path, json_path
