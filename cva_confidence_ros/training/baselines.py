"""Training of the disparity-map baselines (CCNN, LFN, LGC-Net) with ``cva-train --arch``.

Same data, labels, validation, checkpoints and model card as CVA-Net's trainer
(:mod:`cva_confidence_ros.training.trainer`); only the network inputs differ. Every scene is
matched once with the configured matcher, and its winner-takes-all disparity (÷ D) and left
image (grey, ÷ 255) are kept, edge-padded by :data:`~cva_confidence_ros.model.baselines.MARGIN`
px, with the KITTI-criterion labels of the pixels that have ground truth.

Samples are output pixels with a label, drawn as crops:

* ``--mode sparse``: crops of one output pixel, i.e. the 9×9 patches of the published CCNN /
  LFN recipes (``--batch-size`` patches per step), each labelled pixel once before any repeats
  (``training.data.epoch_order``, as CVA-Net's sparse mode);
* ``--mode dense``: ``--crop-size``² outputs per crop with a masked loss (the inputs are the
  crop plus the networks' margins), ``ceil(batch / crop²)`` crops per step.

LGC-Net is trained in Tosi et al.'s two stages within one command: stage 1 trains CCNN (the
local network) and ConfNet together on the same crops (the sum of their two losses; their
parameters are disjoint, so this is two independent trainings sharing the data loading);
stage 2 freezes both, computes their confidence maps of every training scene once, and trains
the fusion network. Each stage runs the configured schedule (``--epochs`` at ``--lr`` then
``--epochs-low-lr`` at the lower rate), so an LGC-Net run has twice as many epochs; an epoch
of a stage draws ``--samples-per-epoch`` or as many samples as that stage's scenes have
labelled pixels.

The two stages learn from disjoint halves of the training scenes (``--fusion-split alternate``,
the default; :func:`split_scenes`): the scenes sorted by name, even positions for CCNN + ConfNet,
odd positions for the fusion. Trained on the parts' own training scenes (``--fusion-split
none``), the fusion learns how over-confident the parts are there, not how they behave on new
scenes, and ends worse than its own parts on unseen data. Of the fusion's epochs, the one with
the best validation AUC is kept (its weights are the ones written). ConfNet
needs crops whose sides are multiples of 16: the crop side is rounded down to one (and
``--mode sparse`` is refused for LGC-Net).

One process (CPU or one GPU); DistributedDataParallel is not offered for these small networks.
"""

from __future__ import annotations

from collections.abc import Callable
import dataclasses
from dataclasses import dataclass
import datetime
import math
import os
from pathlib import Path
import time
from typing import Any, cast

import numpy as np
import torch
from torch import nn
import torch.nn.functional as F

from cva_confidence_ros.datasets import StereoSample
from cva_confidence_ros.errors import ConfigError, ModelError, reason
from cva_confidence_ros.model import ARCHITECTURES, resolve_device, save_weights
from cva_confidence_ros.model.baselines import (
    CONFNET_FACTOR,
    MARGIN,
    TOWER_MARGIN,
    LGCNet,
    network_inputs,
)
from cva_confidence_ros.training.card import hardware_facts, write_model_card
from cva_confidence_ros.training.config import TrainConfig
from cva_confidence_ros.training.data import (
    CropBatch,
    LabelledScene,
    SampleIndex,
    batches,
    dense_crops,
    epoch_order,
    match_and_label,
    sample_index,
    validation_subset,
)

__all__ = [
    'NETWORK_FACTS',
    'DisparityScene',
    'crop_side',
    'split_scenes',
    'gather_planes',
    'pixel_crops',
    'prepare_disparity_scene',
    'train_baseline',
]

#: arch → (card title, one-paragraph description).
NETWORK_FACTS: dict[str, tuple[str, str]] = {
    'ccnn': (
        'CCNN',
        'CCNN (Poggi & Mattoccia, BMVC 2016): per-pixel confidence of the winner-takes-all '
        'disparity, learned from 9×9 patches of the disparity map divided by D (four 3×3 '
        'convolutions of 64, two 1×1 layers of 100, sigmoid output).',
    ),
    'lfn': (
        'LFN',
        'LFN (Fu et al. 2017): late fusion of a disparity tower and a reference-image tower '
        '(each four 3×3 convolutions of 64 on 9×9 patches), then 1×1 layers of 100, 100, 1; '
        'per-pixel confidence of the winner-takes-all disparity.',
    ),
    'lgcnet': (
        'LGC-Net',
        'LGC-Net (Tosi et al., ECCV 2018): local confidence (CCNN on 9×9 disparity patches) '
        'and global confidence (ConfNet, an encoder–decoder with encoders of 64/128/256/512 '
        'on disparity and image), fused by a network of three 3×3-convolution towers and 1×1 '
        'layers of 100, 100, 1.',
    ),
}

_CHOICES = [
    'inputs: WTA disparity ÷ D (NaN → 0) and the left image as grey ÷ 255 (not RGB: the '
    'training data mixes grey and colour pairs)',
    'borders: edge replication, the same in training crops and whole-image inference',
    'loss: binary cross-entropy on labelled pixels; optimiser Adam (β1 0.9, β2 0.999) with '
    "this project's learning-rate schedule instead of the papers' (CPU budget)",
]
#: Validation settings of a checkpoint written before they were saved: the defaults.
_VAL_DEFAULTS: dict[str, Any] = {
    field.name: field.default
    for field in dataclasses.fields(TrainConfig)
    if field.name in ('val_datasets', 'val_synthetic', 'val_pixels')
}
_VAL_DEFAULTS['val_datasets'] = list(_VAL_DEFAULTS['val_datasets'])

_LGC_CHOICES = [
    'local network: CCNN; ConfNet without batch normalisation (batches of 1–2 crops on CPU)',
    'two stages in one run: CCNN + ConfNet (stage 1), then the fusion with both frozen '
    '(stage 2), each with the full epoch schedule',
    'weights stored as float16 (halves the file; loaded back into float32)',
]


@dataclass(eq=False)
class DisparityScene(LabelledScene):
    """One matched scene at the training resolution, as the baselines see it.

    Attributes:
        name: ``dataset/scene``.
        factor: Downscaling factor applied by ``fit_disparity_range``.
        disparity: (H + 16, W + 16) float32 WTA disparity ÷ D, edge-padded by 8 px.
        image: (H + 16, W + 16) float32 grey left image ÷ 255, edge-padded by 8 px.
        labelled: (H, W) bool, True where ground truth is known.
        correct: (H, W) bool, True where the WTA disparity is correct (KITTI criterion).
        local: Stage 2 of LGC-Net only: (H + 16, W + 16) float32 CCNN confidence (edge-padded).
        global_: Stage 2 of LGC-Net only: (H + 16, W + 16) float32 ConfNet confidence.
    """

    name: str
    factor: int
    disparity: np.ndarray
    image: np.ndarray
    labelled: np.ndarray
    correct: np.ndarray
    local: np.ndarray | None = None
    global_: np.ndarray | None = None

    def planes(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Unpadded (1, 1, H, W) disparity and image tensors (for whole-scene inference)."""
        inner = (slice(MARGIN, -MARGIN), slice(MARGIN, -MARGIN))
        return (
            torch.from_numpy(np.ascontiguousarray(self.disparity[inner]))[None, None],
            torch.from_numpy(np.ascontiguousarray(self.image[inner]))[None, None],
        )


def prepare_disparity_scene(
    sample: StereoSample, matcher: str, max_disparity: int
) -> DisparityScene:
    """Shrink a sample until its ground truth fits D, match it, keep disparity, image, labels.

    Raises:
        DataError: No pixel with ground truth after shrinking.
    """
    matched = match_and_label(sample, matcher, max_disparity)
    disparity, image = network_inputs(matched.estimate, matched.fitted.left, max_disparity)
    pad = ((MARGIN, MARGIN), (MARGIN, MARGIN))
    return DisparityScene(
        matched.name,
        matched.factor,
        np.pad(disparity, pad, mode='edge'),
        np.pad(image, pad, mode='edge'),
        matched.labelled,
        matched.correct,
    )


def split_scenes(names: list[str], how: str) -> tuple[list[int], list[int]]:
    """Indices of the scenes for LGC-Net's stage 1 (parts) and stage 2 (fusion).

    Args:
        names: ``dataset/scene`` of every training scene, in loading order.
        how: ``alternate`` (sorted by name: even positions → parts, odd → fusion; disjoint,
            together every scene) or ``none`` (every scene in both).

    Returns:
        ``(parts, fusion)``: sorted index lists into ``names``.

    Raises:
        ConfigError: Unknown ``how``; ``alternate`` with fewer than 2 scenes or repeated names.
    """
    if how == 'none':
        everything = list(range(len(names)))
        return everything, list(everything)
    if how != 'alternate':
        raise ConfigError(f'unknown fusion split {how!r}; expected alternate or none')
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        # E.g. two sizes of one Middlebury scene (trainingQ and trainingH): adjacent in the
        # sorted order, they would land in both halves.
        raise ConfigError(
            f'--fusion-split alternate needs distinct scene names; given more than once: '
            f'{", ".join(repeated)} (a scene in two sizes would train both stages); give each '
            'scene once or use --fusion-split none'
        )
    if len(names) < 2:
        raise ConfigError(
            f'--fusion-split alternate needs at least 2 training scenes; got {len(names)} '
            '(add scenes or use --fusion-split none)'
        )
    order = sorted(range(len(names)), key=lambda i: names[i])
    return sorted(order[0::2]), sorted(order[1::2])


def crop_side(config: TrainConfig, scenes: list[DisparityScene]) -> int:
    """Output side of the training crops (see the module docstring).

    Args:
        config: The run's configuration.
        scenes: The prepared training scenes; none (before preparing) checks the options only.

    Raises:
        ConfigError: LGC-Net with ``--mode sparse``, or crops (``--crop-size`` or the smallest
            scene side) smaller than 16 px.
    """
    if config.mode == 'sparse':
        if config.arch == 'lgcnet':
            raise ConfigError(
                'lgcnet trains ConfNet on image crops: use --mode dense with a --crop-size '
                f'that is a multiple of {CONFNET_FACTOR}'
            )
        return 1
    sides = [min(s.shape) for s in scenes]
    side = min([config.crop_size, *sides])
    if config.arch == 'lgcnet':
        side -= side % CONFNET_FACTOR
        if side < CONFNET_FACTOR:
            raise ConfigError(
                f'lgcnet needs crops of at least {CONFNET_FACTOR} px (ConfNet pools 4 times); '
                f'got --crop-size {config.crop_size}'
                + (f' and a smallest scene side of {min(sides)}' if sides else '')
            )
    return side


def pixel_crops(index: SampleIndex, n_samples: int, seed: int, epoch: int) -> CropBatch:
    """``--mode sparse``: one-pixel crops of one epoch, each labelled pixel of ``index`` once
    before any repeats, shuffled by (seed, epoch) (``training.data.epoch_order``).

    Returns:
        A ``CropBatch`` of ``n_samples`` crops of side 1, one labelled output each.

    Raises:
        DataError: ``index`` is empty.
    """
    order = epoch_order(len(index), n_samples, seed, epoch)
    return CropBatch(
        index.scene[order], index.ys[order], index.xs[order], np.ones(order.size, np.int32)
    )


def gather_planes(
    scenes: list[DisparityScene],
    crops: Any,
    rows: np.ndarray,
    side: int,
    margin: int,
    names: tuple[str, ...] = ('disparity', 'image'),
) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor]:
    """Input planes, targets and loss masks of the chosen crops.

    Args:
        scenes: The prepared scenes.
        crops: A ``training.data.CropBatch`` (top-left output corners per crop).
        rows: (B,) indices into ``crops``.
        side: Output side of a crop.
        margin: Input pixels on each side beyond the outputs (4 for a tower, 0 for ConfNet).
        names: Which padded planes of the scenes to cut (``disparity``, ``image``, ``local``,
            ``global_``).

    Returns:
        ``(planes, targets, mask)``: per name a (B, 1, side + 2·margin, side + 2·margin)
        float32 tensor; (B, side, side) float32 targets (1 = correct); (B, side, side) bool.
    """
    span = side + 2 * margin
    planes = [np.empty((len(rows), 1, span, span), np.float32) for _ in names]
    targets = np.empty((len(rows), side, side), np.float32)
    mask = np.empty((len(rows), side, side), bool)
    for out, row in enumerate(rows):
        scene = scenes[int(crops.scene[row])]
        y0, x0 = int(crops.y0[row]), int(crops.x0[row])
        top, left = y0 + MARGIN - margin, x0 + MARGIN - margin
        for plane, name in zip(planes, names, strict=True):
            plane[out, 0] = getattr(scene, name)[top : top + span, left : left + span]
        targets[out] = scene.correct[y0 : y0 + side, x0 : x0 + side]
        mask[out] = scene.labelled[y0 : y0 + side, x0 : x0 + side]
    return [torch.from_numpy(p) for p in planes], torch.from_numpy(targets), torch.from_numpy(mask)


def _masked_bce(logits: torch.Tensor, targets: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    logits = logits[:, 0]
    if not bool(mask.any()):
        return logits.sum() * 0.0
    return F.binary_cross_entropy_with_logits(logits[mask], targets[mask])


def _auc(net: nn.Module, scenes: list[DisparityScene], subsets: list[Any], device: Any,
         part: str | None = None, epoch: int = 0, lr: float = 0.0,
         out: Path = Path()) -> dict[str, float | None]:
    """Validation scores of ``net`` (or of LGC-Net's ``part``, ``local`` or ``global``) after
    ``epoch`` (0-based; ``lr`` and ``out`` for the message of a diverged run).

    Raises:
        ModelError: A confidence is NaN or infinite (the network diverged).
    """
    from cva_confidence_ros.metrics import auc_scores
    from cva_confidence_ros.training.trainer import _diverged

    confidences, wrongs = [], []
    net.eval()
    with torch.no_grad():
        for scene, (ys, xs) in zip(scenes, subsets, strict=True):
            if ys.size == 0:
                continue
            d, i = (t.to(device) for t in scene.planes())
            if part == 'local':
                assert isinstance(net, LGCNet)  # parts are LGC-Net's (stage 'parts')
                conf = net.local.dense_confidence(d, i)
            elif part == 'global':
                assert isinstance(net, LGCNet)
                conf = net.confnet.dense_confidence(d, i)
            else:
                # Every baseline network has dense_confidence(disparity, image).
                dense = cast('Callable[[torch.Tensor, torch.Tensor], torch.Tensor]',
                             net.dense_confidence)
                conf = dense(d, i)
            confidences.append(conf[0, 0].cpu().numpy()[ys, xs])
            wrongs.append(~scene.correct[ys, xs])
    net.train()
    if not confidences:
        return {'val_auc': None, 'val_auc_opt': None, 'val_error_rate': None, 'val_high': None}
    confidence = np.concatenate(confidences)
    bad = int(np.count_nonzero(~np.isfinite(confidence)))
    if bad:
        # auc_scores would refuse them as bad input, which says nothing of the training.
        name = {'local': 'CCNN ', 'global': 'ConfNet '}.get(part or '', '')
        raise _diverged(
            f'after epoch {epoch + 1}, {bad} of {confidence.size} {name}validation confidences '
            'are NaN or infinite',
            epoch,
            lr,
            out,
        )
    scores = auc_scores(confidence, np.concatenate(wrongs))
    return {
        **{f'val_{key}': float(scores[key]) for key in ('auc', 'auc_opt', 'error_rate')},
        # The model card's share of outputs >= 0.5, as CVA-Net's trainer records it.
        'val_high': float(np.mean(confidence >= 0.5)),
    }


def _freeze_parts(net: LGCNet, scenes: list[DisparityScene], device: Any) -> None:
    """Stage 2 inputs: CCNN and ConfNet confidence of every training scene, computed once."""
    net.eval()
    with torch.no_grad():
        for scene in scenes:
            d, i = (t.to(device) for t in scene.planes())
            _, local4, global4 = net.parts(d, i)
            pad = ((TOWER_MARGIN, TOWER_MARGIN), (TOWER_MARGIN, TOWER_MARGIN))
            scene.local = np.pad(local4[0, 0].cpu().numpy(), pad, mode='edge')
            scene.global_ = np.pad(global4[0, 0].cpu().numpy(), pad, mode='edge')
    net.train()


def _stage_of(config: TrainConfig, epoch: int) -> tuple[str, int]:
    """(stage name, epoch index within the stage) of a 0-based run epoch."""
    if config.arch != 'lgcnet':
        return 'single', epoch
    if epoch < config.total_epochs:
        return 'parts', epoch
    return 'fusion', epoch - config.total_epochs


def _schedule(config: TrainConfig) -> list[tuple[str, float]]:
    """(stage, learning rate) of every run epoch: LGC-Net runs the schedule twice, CCNN + ConfNet
    (``parts``) then the fusion; CCNN and LFN once (``single``)."""
    total = config.total_epochs * (2 if config.arch == 'lgcnet' else 1)
    plan = []
    for epoch in range(total):
        stage, stage_epoch = _stage_of(config, epoch)
        plan.append((stage, config.lr_at(stage_epoch)))
    return plan


def _optimiser(net: nn.Module, stage: str, lr: float) -> torch.optim.Optimizer:
    if stage == 'parts':
        assert isinstance(net, LGCNet)
        params = list(net.local.parameters()) + list(net.confnet.parameters())
    elif stage == 'fusion':
        assert isinstance(net, LGCNet)
        params = list(net.fusion.parameters())
    else:
        params = list(net.parameters())
    return torch.optim.Adam(params, lr=lr, betas=(0.9, 0.999))


def _stage_logits(
    net: nn.Module, stage: str, scenes: list[DisparityScene], crops: Any, step: np.ndarray,
    side: int, device: Any,
) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor]:
    """Logits of the networks ``stage`` trains (CCNN and ConfNet in ``parts``, else one), each
    (B, 1, side, side), on the crops ``step``, with their targets and loss masks."""
    if stage == 'fusion':
        planes, targets, mask = gather_planes(
            scenes, crops, step, side, TOWER_MARGIN, ('disparity', 'local', 'global_')
        )
        planes = [p.to(device) for p in planes]
        assert isinstance(net, LGCNet)  # stage 'fusion' is LGC-Net's
        return [net.fusion.forward_logits(*planes)], targets.to(device), mask.to(device)
    planes, targets, mask = gather_planes(scenes, crops, step, side, TOWER_MARGIN)
    mask, targets = mask.to(device), targets.to(device)
    planes = [p.to(device) for p in planes]
    if stage == 'single':
        forward_logits = cast(  # CCNN or LFN
            'Callable[[torch.Tensor, torch.Tensor], torch.Tensor]', net.forward_logits
        )
        return [forward_logits(*planes)], targets, mask
    assert isinstance(net, LGCNet)  # stage 'parts' is LGC-Net's
    inner = [p[:, :, TOWER_MARGIN:-TOWER_MARGIN, TOWER_MARGIN:-TOWER_MARGIN] for p in planes]
    logits = [net.local.forward_logits(*planes), net.confnet.forward_logits(*inner)]
    return logits, targets, mask


def _step_loss(
    net: nn.Module, stage: str, scenes: list[DisparityScene], crops: Any, step: np.ndarray,
    side: int, device: Any,
) -> tuple[torch.Tensor, int]:
    logits, targets, mask = _stage_logits(net, stage, scenes, crops, step, side, device)
    loss = _masked_bce(logits[0], targets, mask)
    for more in logits[1:]:  # parts: CCNN's loss + ConfNet's
        loss = loss + _masked_bce(more, targets, mask)
    return loss, int(mask.sum())


def _check_finite_outputs(
    net: nn.Module, stage: str, scenes: list[DisparityScene], index: SampleIndex, side: int,
    device: Any, epoch: int, lr: float, out: Path,
) -> str | None:
    """Stop a run whose last steps left weights with non-finite outputs, as CVA-Net's trainer
    does: the loss of an epoch is that of the weights before each step, so it stays finite
    when only the last step diverged, and the checkpoint and weights file would take the
    broken weights (an LGC-Net stage 1 so broken also feeds NaN maps to the fusion).

    The networks the stage trains run in eval mode on crops of the run's side around up to
    ``_PROBE_PIXELS`` labelled pixels spread over the stage's index (one crop per
    ``_PROBE_PIXELS`` outputs at the most); their labelled outputs are checked.

    Returns what is wrong with a network that gives one confidence at every probed pixel,
    correct and wrong ones (a collapse, as CVA-Net's trainer finds one: see
    ``trainer.one_confidence``; the caller refuses to write such weights), or None.

    Raises:
        ModelError: Some logit is NaN or infinite.
    """
    from cva_confidence_ros.training.trainer import (
        _PROBE_PIXELS,
        _diverged,
        collapse_message,
        one_confidence,
    )

    count = min(len(index), max(1, _PROBE_PIXELS // side**2))
    chosen = np.linspace(0, len(index) - 1, count).round().astype(np.int64)
    number = index.scene[chosen]
    heights = np.array([scenes[int(n)].shape[0] for n in number])
    widths = np.array([scenes[int(n)].shape[1] for n in number])
    crops = CropBatch(
        number.astype(np.int32),
        np.minimum(index.ys[chosen], heights - side).astype(np.int32),
        np.minimum(index.xs[chosen], widths - side).astype(np.int32),
        np.ones(count, np.int32),
    )
    net.eval()
    try:
        with torch.no_grad():
            logits, targets, mask = _stage_logits(
                net, stage, scenes, crops, np.arange(count), side, device
            )
    finally:
        net.train()
    bad = sum(int((~torch.isfinite(part[:, 0][mask])).sum()) for part in logits)
    if bad:
        name = {'parts': 'CCNN and ConfNet', 'fusion': 'the fusion network'}.get(
            stage, 'the network'
        )
        raise _diverged(
            f'after epoch {epoch + 1}, {bad} of {int(mask.sum()) * len(logits)} logits of '
            f'{name} at training pixels are NaN or infinite',
            epoch,
            lr,
            out,
        )
    # Whether the probe's inputs vary: the disparity (CCNN reads nothing else), and the
    # parts' maps that the fusion reads too.
    names = ('disparity', 'local', 'global_') if stage == 'fusion' else ('disparity',)
    planes, _, _ = gather_planes(scenes, crops, np.arange(count), side, TOWER_MARGIN, names)
    vary = any(bool((plane != plane.flatten()[0]).any()) for plane in planes)
    parts = {'parts': ['CCNN', 'ConfNet'], 'fusion': ['the fusion network']}.get(
        stage, ['the network']
    )
    for name, part in zip(parts, logits, strict=True):
        confidence = torch.sigmoid(part[:, 0][mask].float())
        if one_confidence(confidence, targets[mask], vary):
            return collapse_message(epoch, name, float(confidence[0]), confidence.numel())
    return None


def train_baseline(config: TrainConfig, command: str = '') -> dict[str, Any]:
    """Train CCNN, LFN or LGC-Net as configured; write checkpoints, log, weights, model card.

    Called by :func:`cva_confidence_ros.training.trainer.train` for those architectures; same
    arguments, return value and errors.
    """
    from cva_confidence_ros.training.trainer import (
        CHECKPOINT_NAME,
        SamePairs,
        _diverged,
        _load_checkpoint,
        _load_samples,
        _Log,
        _prepare,
        _prepare_validation,
        _progress,
        _save_checkpoint,
        _scene_facts,
        _write_history,
        check_finite_loss,
        check_run_setup,
        training_pairs,
        weights_out_path,
    )

    if int(os.environ.get('WORLD_SIZE', '1')) > 1:
        raise ConfigError(
            f'--arch {config.arch} trains in one process; run it without torchrun'
        )
    if config.init_weights or config.teacher:
        raise ConfigError(
            f'--arch {config.arch} trains from scratch: --init-weights and --teacher are for '
            'the cost-volume networks (cvanet, cvanet_lite, cvanet_fast)'
        )
    check_run_setup(config)
    device = resolve_device(config.device)
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    log = _Log(out / 'train.log', True)
    log(f'cva-train: {command or config.to_dict()}')
    started = time.perf_counter()
    # The checkpoint is checked before the data are prepared: a refused resume costs nothing.
    checkpoint = out / CHECKPOINT_NAME
    state: dict[str, Any] | None = None
    if config.resume and checkpoint.is_file():
        state = _load_checkpoint(checkpoint, config, _schedule)
        saved = {'fusion_split': 'none', **_VAL_DEFAULTS, **state['config']}
        current = config.to_dict()
        # The fusion epoch kept is the one of best validation AUC: once one is recorded, the
        # later epochs must be validated on the same pixels to be compared with it.
        keys = ['fusion_split'] + (list(_VAL_DEFAULTS) if state.get('best_fusion') else [])
        changed = [k for k in keys if saved[k] != current[k]]
        if config.arch == 'lgcnet' and changed:
            raise ConfigError(
                f'cannot resume from {checkpoint}: the run was started with other settings ('
                + ', '.join(f'{k}: {saved[k]!r} → {current[k]!r}' for k in changed)
                + ')'
                + (', and its best fusion epoch so far was chosen on the saved validation '
                   'pixels' if changed != ['fusion_split'] else '')
                + '; use another --out folder or the original settings'
            )

    # Both listed before either is prepared: a missing validation scene costs no matching.
    loaders, val_loaders = _load_samples(config, False, log), _load_samples(config, True, log)
    split = config.fusion_split if config.arch == 'lgcnet' else 'none'
    split_scenes([label for label, _ in loaders], split)  # refused now, not after preparing
    if config.arch == 'lgcnet':
        crop_side(config, [])  # sparse mode or too small a --crop-size: refused now
    pairs: dict[str, str] = {}  # the pairs taken, to take each once
    same = None if state is None else SamePairs(checkpoint, state)
    scenes = _prepare(loaders, config, False, log, prepare_disparity_scene, pairs, same)
    train_pairs = training_pairs(pairs)
    index = sample_index(scenes)
    parts_at, fusion_at = split_scenes([s.name for s in scenes], split)
    stage_scenes = {
        'single': scenes,
        'parts': [scenes[i] for i in parts_at],
        'fusion': [scenes[i] for i in fusion_at],
    }
    stage_index = {
        'single': index,
        'parts': sample_index(stage_scenes['parts']),
        'fusion': sample_index(stage_scenes['fusion']),
    }
    if config.arch == 'lgcnet':
        log(f'fusion split {split}: parts on {len(parts_at)} scenes '
            f'({len(stage_index["parts"])} labelled px), fusion on {len(fusion_at)} scenes '
            f'({len(stage_index["fusion"])} labelled px)')
    same_val = None if state is None else SamePairs(checkpoint, state, validation=True)
    val_scenes, val_pairs = _prepare_validation(
        val_loaders, config, log, prepare_disparity_scene, pairs, same_val
    )
    val_subsets = validation_subset(val_scenes, config.val_pixels, config.seed)
    side = crop_side(config, scenes)
    # An epoch of a stage draws as many samples as that stage has labelled pixels (half of
    # them each with the alternate split), or --samples-per-epoch.
    stage_samples = {name: config.samples_per_epoch or len(at) for name, at in stage_index.items()}
    n_samples = stage_samples['parts' if config.arch == 'lgcnet' else 'single']
    per_epoch = (f'{n_samples} (parts) / {stage_samples["fusion"]} (fusion)'
                 if config.arch == 'lgcnet' else f'{n_samples}')
    log(
        f'{len(scenes)} training scenes, {len(index)} labelled pixels, '
        f'{index.fraction_wrong:.1%} labelled wrong; {per_epoch} samples per epoch '
        f'({config.mode} mode, crops of {side}² outputs); {len(val_scenes)} validation scenes'
    )

    torch.manual_seed(config.seed)
    net = ARCHITECTURES.get(config.arch)({'max_disparity': config.max_disparity}).to(device)
    epochs_total = len(_schedule(config))
    history: list[dict[str, Any]] = []
    start_epoch = 0
    previous_wall = 0.0
    saved_optimiser: tuple[str, Any] | None = None
    best: dict[str, Any] | None = None  # LGC-Net: the fusion epoch with the best val AUC
    collapsed_at: dict[int, str] = {}  # run epoch → how its network collapsed
    if state is not None:
        try:
            net.load_state_dict(state['model'])
        except (KeyError, TypeError, ValueError, RuntimeError) as exc:
            raise ModelError(
                f'checkpoint {checkpoint} does not fit this network ({reason(exc)})'
            ) from exc
        history = list(state['history'])
        start_epoch = int(state['epoch'])
        previous_wall = float(state.get('wall_time_s', 0.0))
        saved_optimiser = (str(state.get('stage', 'single')), state['optimizer'])
        best = state.get('best_fusion')
        log(f'resumed from {checkpoint} after epoch {start_epoch}')
        # A run stopped between its checkpoint and history.json left that one short; a resume
        # with no epoch left to train would never write it.
        _write_history(out, history)
    elif config.resume:
        log(f'--resume: no checkpoint in {out}, starting from scratch')

    optimiser: torch.optim.Optimizer | None = None
    current_stage = ''
    for epoch in range(start_epoch, epochs_total):
        stage, stage_epoch = _stage_of(config, epoch)
        if stage != current_stage:
            optimiser = _optimiser(net, stage, config.lr)
            if saved_optimiser is not None and saved_optimiser[0] == stage:
                optimiser.load_state_dict(saved_optimiser[1])
            saved_optimiser = None
            if stage == 'fusion':
                tic = time.perf_counter()
                assert isinstance(net, LGCNet)
                _freeze_parts(net, stage_scenes['fusion'], device)
                log(f'stage 2: CCNN and ConfNet frozen, their maps of '
                    f'{len(stage_scenes["fusion"])} scenes '
                    f'computed in {time.perf_counter() - tic:.1f} s')
            current_stage = stage
        assert optimiser is not None
        lr = config.lr_at(stage_epoch)
        for group in optimiser.param_groups:
            group['lr'] = lr
        torch.manual_seed(config.seed * 1_000_003 + epoch * 7919 + 1)
        if config.mode == 'sparse':
            # dense_crops would redraw a permutation of all pixels per 4096 crops: a quarter
            # to a third of the pixels unseen, and minutes an epoch on real data sets.
            crops = pixel_crops(stage_index[stage], stage_samples[stage], config.seed, epoch)
        else:
            crops = dense_crops(
                stage_scenes[stage],
                stage_index[stage], stage_samples[stage], side, config.seed, epoch
            )
        per_step = max(1, math.ceil(config.batch_size / side**2))
        steps = list(batches(np.arange(len(crops.scene)), per_step))
        net.train()
        tic = time.perf_counter()
        loss_sum, seen = 0.0, 0
        description = f'epoch {epoch + 1}/{epochs_total}' + (
            f' ({stage})' if stage != 'single' else ''
        )
        with _progress(int(crops.n_labelled.sum()), description, config.progress) as bar:
            for step in steps:
                loss, count = _step_loss(
                    net, stage, stage_scenes[stage], crops, step, side, device
                )
                optimiser.zero_grad(set_to_none=True)
                loss.backward()
                optimiser.step()
                loss_sum += float(loss.detach()) * count
                seen += count
                bar.update(count)
                elapsed = time.perf_counter() - tic
                bar.set_postfix(loss=f'{loss_sum / max(1, seen):.4f}', sps=f'{seen / elapsed:.0f}')
        seconds = time.perf_counter() - tic
        check_finite_loss(loss_sum / max(1, seen), epoch, lr, out)
        collapsed = _check_finite_outputs(
            net, stage, stage_scenes[stage], stage_index[stage], side, device, epoch, lr, out
        )
        if collapsed:
            collapsed_at[epoch + 1] = collapsed
        record: dict[str, Any] = {
            'epoch': epoch + 1,
            'lr': lr,
            'train_loss': loss_sum / max(1, seen),
            'samples': seen,
            'seconds': seconds,
            'samples_per_s': seen / max(seconds, 1e-9),
        }
        if stage != 'single':
            record['stage'] = stage
        if stage == 'parts':
            local = _auc(net, val_scenes, val_subsets, device, 'local', epoch, lr, out)
            global_ = _auc(net, val_scenes, val_subsets, device, 'global', epoch, lr, out)
            record.update(
                {
                    'val_auc': None,
                    'val_auc_local': local['val_auc'],
                    'val_auc_global': global_['val_auc'],
                    'val_auc_opt': local['val_auc_opt'],
                    'val_error_rate': local['val_error_rate'],
                }
            )
        else:
            record.update(_auc(net, val_scenes, val_subsets, device, None, epoch, lr, out))
        history.append(record)
        if stage == 'fusion' and record['val_auc'] is not None and (
            best is None or record['val_auc'] < best['val_auc']
        ):
            assert isinstance(net, LGCNet)
            best = {
                'epoch': epoch + 1,
                'val_auc': record['val_auc'],
                'fusion': {k: v.detach().cpu().clone()
                           for k, v in net.fusion.state_dict().items()},
            }
        # The weights written are the last epoch's (LGC-Net: its best fusion epoch's): not
        # those of a collapsed network, as CVA-Net's trainer refuses them.
        kept = epoch + 1 if best is None else int(best['epoch'])
        if epoch + 1 == epochs_total and kept in collapsed_at:
            raise _diverged(collapsed_at[kept], epoch, lr, out)
        if collapsed:
            log(f'warning: {collapsed} (lr {lr:g}); lower --lr unless later epochs undo it')
        wall = previous_wall + time.perf_counter() - started
        _save_checkpoint(
            checkpoint,
            {
                'format': 1,
                'epoch': epoch + 1,
                'stage': stage,
                'model': {k: v.detach().cpu() for k, v in net.state_dict().items()},
                'optimizer': optimiser.state_dict(),
                'history': history,
                'best_fusion': best,
                'config': config.to_dict(),
                'wall_time_s': wall,
                'train_pairs': train_pairs,
                'val_pairs': val_pairs,
                'weights_out_path': weights_out_path(config),
            },
        )
        _write_history(out, history)
        val = record.get('val_auc')
        parts = ''
        if stage == 'parts' and record['val_auc_local'] is not None:
            parts = (f', val AUC CCNN {record["val_auc_local"]:.4f} / ConfNet '
                     f'{record["val_auc_global"]:.4f}')
        log(
            f'{description}: lr {lr:.1e}, loss {record["train_loss"]:.4f}, {seen} samples in '
            f'{seconds:.1f} s ({record["samples_per_s"]:.1f}/s)'
            + (f', val AUC {val:.4f} (optimal {record["val_auc_opt"]:.4f})'
               if val is not None else parts)
        )

    selected = None
    if best is not None and isinstance(net, LGCNet) and history:
        net.fusion.load_state_dict(best['fusion'])
        selected = {'epoch': int(best['epoch']), 'val_auc': float(best['val_auc'])}
        log(f'fusion: kept epoch {selected["epoch"]} (best val AUC {selected["val_auc"]:.4f})')
    wall = previous_wall + time.perf_counter() - started
    summary = _summary(config, scenes, val_scenes, val_subsets, index, n_samples, side,
                       history, device, wall, command, _scene_facts)
    if config.arch == 'lgcnet':
        summary['fusion_split'] = split
        summary['fusion_samples_per_epoch'] = stage_samples['fusion']
        summary['parts_scenes'] = [s.name for s in stage_scenes['parts']]
        summary['fusion_scenes'] = [s.name for s in stage_scenes['fusion']]
        summary['network_notes'].append(
            f'fusion split {split}: CCNN + ConfNet trained on {len(parts_at)} scenes '
            f'({", ".join(summary["parts_scenes"])}), the fusion on '
            + (f'{len(fusion_at)} others ({", ".join(summary["fusion_scenes"])})'
               if split != 'none' else 'the same scenes')
        )
        if selected is not None:
            summary['fusion_epoch_selected'] = selected['epoch']
            summary['final_val_auc'] = selected['val_auc']
            summary['final_val_high'] = next(
                (r.get('val_high') for r in history if r['epoch'] == selected['epoch']), None
            )
            summary['network_notes'].append(
                f'fusion weights of run epoch {selected["epoch"]}, the stage-2 epoch with the '
                f'best validation AUC ({selected["val_auc"]:.4f})'
            )
    if config.weights_out:
        to_save = net
        if config.arch == 'lgcnet':
            import copy

            to_save = copy.deepcopy(net).half()
        path = save_weights(to_save, config.weights_out, summary)
        md_path, json_path = write_model_card(path, summary)
        log(f'wrote {path}, {md_path} and {json_path}')
    return summary


def _summary(
    config: TrainConfig, scenes: list[DisparityScene], val_scenes: list[DisparityScene],
    val_subsets: list[Any], index: Any, n_samples: int, side: int,
    history: list[dict[str, Any]], device: Any, wall: float, command: str, scene_facts: Any,
) -> dict[str, Any]:
    last = history[-1] if history else {}
    title, description = NETWORK_FACTS[config.arch]
    notes = list(_CHOICES) + (list(_LGC_CHOICES) if config.arch == 'lgcnet' else [])
    if config.arch == 'ccnn':
        # CCNN's tower has one input plane: the image is passed and ignored.
        notes[0] = 'inputs: WTA disparity ÷ D (NaN → 0) only (the image is passed and ignored)'
    notes.append(
        'samples: ' + ('9×9 patches, one labelled output each' if side == 1 else
                       f'crops of {side}² outputs, masked loss on the labelled ones')
    )
    for record in history:
        if record.get('stage') == 'parts' and record.get('val_auc_local') is not None:
            notes.append(
                f'stage 1 epoch {record["epoch"]}: val AUC CCNN {record["val_auc_local"]:.4f},'
                f' ConfNet {record["val_auc_global"]:.4f}'
            )
    summary: dict[str, Any] = {
        'arch': config.arch,
        'network': title,
        'network_description': description,
        'network_notes': notes,
        'matcher': config.matcher,
        'max_disparity': config.max_disparity,
        'mode': config.mode,
        'crop_size': side,
        'datasets': list(config.datasets),
        'synthetic': config.synthetic,
        'synthetic_size': list(config.synthetic_hw),
        'scenes': scene_facts(scenes),
        'labelled_pixels': len(index),
        'fraction_wrong': index.fraction_wrong,
        'val_datasets': list(config.val_datasets),
        'val_data_root': config.val_data_root,
        'val_synthetic': config.val_synthetic,
        'val_scenes': scene_facts(val_scenes),
        'val_pixels': int(sum(ys.size for ys, _ in val_subsets)),
        'samples_per_epoch': n_samples,
        'samples_seen': int(sum(r['samples'] for r in history)),
        'epochs': config.epochs,
        'epochs_low_lr': config.epochs_low_lr,
        'stages': 2 if config.arch == 'lgcnet' else 1,
        'batch_size': config.batch_size,
        'lr': config.lr,
        'lr_low': config.lr * config.low_lr_factor,
        'seed': config.seed,
        'hardware': hardware_facts(device, 1),
        'wall_time_s': wall,
        'command': command,
        'final_train_loss': last.get('train_loss'),
        'final_val_auc': last.get('val_auc'),
        'final_val_auc_opt': last.get('val_auc_opt'),
        'final_val_error_rate': last.get('val_error_rate'),
        'final_val_high': last.get('val_high'),
        'history': history,
        'date': datetime.date.today().isoformat(),
    }
    if config.arch == 'lgcnet':
        summary['confnet_width'] = 32
        summary['storage'] = 'float16'
    return summary
