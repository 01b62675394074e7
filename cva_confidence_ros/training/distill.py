"""Knowledge distillation and warm starts for ``cva-train``.

Distillation (``--teacher PATH --distill-weight A``): a trained network (normally the paper's
CVA-Net) runs on the same batch as the student, folded and in eval mode, without gradients.
On every labelled output the loss is

    (1 − A) · BCE(student, label) + A · BCE(student, teacher probability)

so A = 0 is plain training and A = 1 imitates the teacher only. The teacher's probability is
a soft target: it also tells the student how sure the teacher is. Unlabelled outputs of a
dense-mode crop stay out of the loss, as in plain training: the shipped teachers are weaker
than the labels (see the model cards), so the labels should keep the last word, and sparse and
dense mode then train on the same pixels.

Warm start (``--init-weights PATH``): weights of the same architecture are copied into the
network before the first epoch (continued training, e.g. of CVA-Net). Weights of another depth
D are transferred (:func:`transfer_state`): the convolutions act the same way at every
disparity and are copied; the first fully-connected layer spans the whole fused depth, so the
disparities both depths share get the source's kernel and the rest zeros — at the start the
network decides from the disparities the source saw, and training teaches it the others.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, cast

import torch
from torch import nn
import torch.nn.functional as F

from cva_confidence_ros.checks import is_real
from cva_confidence_ros.errors import ConfigError, InputError, ModelError
from cva_confidence_ros.model import CVANet, fold_batchnorm, load_weights

__all__ = [
    'distillation_loss',
    'load_init_weights',
    'load_teacher',
    'teacher_logits',
    'transfer_state',
]


def load_teacher(
    path: str, matcher: str, max_disparity: int, device: torch.device
) -> tuple[nn.Module, dict[str, Any]]:
    """Load the teacher network of a distillation run, folded and frozen.

    Args:
        path: Weights file of any registered architecture (normally CVA-Net).
        matcher: The matcher the student learns; the teacher must be trained for it too.
        max_disparity: The student's D; the teacher must take the same cost volumes.
        device: Where the teacher runs (the training device).

    Returns:
        ``(teacher, meta)``: an inference module mapping (B, 1, D, H + 12, W + 12) to (B, H, W)
        logits through ``forward_logits``, and the teacher's stored meta.

    Raises:
        ModelError: Missing or corrupt file, or weights for another matcher or depth.
        ConfigError: The architecture cannot be folded for inference.
    """
    net, meta = load_weights(path, matcher=matcher, max_disparity=max_disparity, arch=None)
    if isinstance(net, CVANet):
        teacher: nn.Module = fold_batchnorm(net)
    elif callable(getattr(net, 'fold_batchnorm', None)):
        teacher = net.fold_batchnorm()
    else:
        raise ConfigError(
            f'teacher {path} (arch {meta.get("arch")!r}) has no fold_batchnorm(); '
            'expected a cost-volume network such as CVA-Net'
        )
    teacher.to(device).eval().requires_grad_(False)
    return teacher, meta


def teacher_logits(teacher: nn.Module, volumes: torch.Tensor) -> torch.Tensor:
    """The teacher's (B, H, W) logits for (B, 1, D, H + 12, W + 12) inputs, without a graph.

    The teacher runs in eval mode whatever its mode (and is given its mode back): in training
    mode an unfolded network would normalise by the batch's statistics, move its running
    statistics and drop out, so its targets would change from call to call.
    """
    # load_teacher returns a folded cost-volume network, which has forward_logits.
    forward_logits = cast('Callable[[torch.Tensor], torch.Tensor]', teacher.forward_logits)
    was_training = teacher.training
    teacher.eval()
    try:
        with torch.no_grad():
            return forward_logits(volumes)
    finally:
        teacher.train(was_training)


def distillation_loss(
    logits: torch.Tensor,
    targets: torch.Tensor,
    teacher: torch.Tensor | None,
    weight: float,
) -> torch.Tensor:
    """Mean of (1 − A)·BCE(logits, targets) + A·BCE(logits, sigmoid(teacher)).

    Args:
        logits: (N,) student logits of the labelled outputs.
        targets: (N,) labels, 1 = correct disparity (float, or bool / integer 0 and 1).
        teacher: (N,) teacher logits of the same outputs, or None (then A must be 0); taken
            as constant targets (detached).
        weight: A in [0, 1].

    Returns:
        The scalar loss; 0 (still tied to ``logits``, so backward and DDP's gradient
        exchange run) when there are no outputs, where a mean would be NaN.

    Raises:
        ConfigError: ``weight`` is not a real number in [0, 1], or is > 0 without a teacher.
        InputError: ``targets`` or ``teacher`` not shaped like ``logits``.
    """
    if not is_real(weight) or not 0.0 <= weight <= 1.0:
        raise ConfigError(f'distill weight must be in [0, 1]; got {weight!r}')
    for name, tensor in (('targets', targets), ('teacher logits', teacher)):
        if tensor is not None and tensor.shape != logits.shape:
            raise InputError(
                f'{name} must have the shape of the student logits {tuple(logits.shape)}; '
                f'got {tuple(tensor.shape)}'
            )
    if not targets.is_floating_point():  # bool or integer labels, 1 = correct
        targets = targets.to(logits.dtype)
    if logits.numel() == 0:
        if teacher is None and weight != 0.0:
            raise ConfigError('a distill weight > 0 needs teacher logits')
        return logits.sum() * 0.0
    hard = F.binary_cross_entropy_with_logits(logits, targets)
    if teacher is None or weight == 0.0:
        if weight != 0.0:
            raise ConfigError('a distill weight > 0 needs teacher logits')
        return hard
    # The teacher's probability is a target: no gradient flows back into the teacher.
    soft = F.binary_cross_entropy_with_logits(logits, torch.sigmoid(teacher.detach().float()))
    return (1.0 - weight) * hard + weight * soft


def transfer_state(
    source: dict[str, torch.Tensor], target: dict[str, torch.Tensor]
) -> dict[str, torch.Tensor]:
    """The tensors of ``source`` shaped for a network whose state is ``target``.

    Tensors of equal shape are taken as they are. A tensor that differs only along its depth
    axis (axis 2, the disparity axis of the kernels that span the fused depth) gets the
    source's values on the depth indices both have — index i is the same disparity in any D —
    and zeros beyond them (or is cut, from a deeper source).

    Raises:
        ModelError: Other tensor names, or shapes that differ elsewhere than the depth axis.
    """
    if set(source) != set(target):
        missing = sorted(set(target) - set(source))
        extra = sorted(set(source) - set(target))
        raise ModelError(f'the weights do not fit this network: missing {missing}, extra {extra}')
    state = {}
    for key, value in source.items():
        want = target[key]
        if value.shape == want.shape:
            state[key] = value
            continue
        same_elsewhere = (
            value.dim() == want.dim() >= 3
            and value.shape[:2] == want.shape[:2]
            and value.shape[3:] == want.shape[3:]
        )
        if not same_elsewhere:
            raise ModelError(
                f'{key}: stored shape {tuple(value.shape)} does not fit {tuple(want.shape)}'
            )
        depth = min(value.shape[2], want.shape[2])
        moved = torch.zeros_like(want)
        moved[:, :, :depth] = value[:, :, :depth]
        state[key] = moved
    return state


def load_init_weights(net: nn.Module, path: str, arch: str) -> dict[str, Any]:
    """Copy the weights of ``path`` into ``net`` (same architecture; D may differ).

    Weights of another depth D are transferred by :func:`transfer_state`.

    Returns:
        The stored meta of the weights (for the training summary).

    Raises:
        ModelError: Missing or corrupt file or other architecture.
    """
    source, meta = load_weights(Path(path), arch=arch)
    net.load_state_dict(transfer_state(source.state_dict(), net.state_dict()))
    return meta
