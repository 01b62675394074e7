"""``torch.hub`` entry points: the confidence networks with their shipped weights, and the
whole stereo pipeline, without installing the package.

    import torch
    net = torch.hub.load('<owner>/cva_confidence_ros', 'cvanet', matcher='census_sgm')
    confidence = net.predict(cost_volume)  # (D, H, W) in [0, 1] → (H, W) in (0, 1)
    pipeline = torch.hub.load('<owner>/cva_confidence_ros', 'pipeline', matcher='census_bm')
    result = pipeline.process(left, right)  # disparity, confidence, valid, ...

A checkout works the same with ``torch.hub.load(PATH, 'cvanet', source='local')``;
``torch.hub.list('<owner>/cva_confidence_ros')`` names the entries and ``torch.hub.help``
shows their options. The weights
are the files in ``models/`` next to this file, the ones ``cva-evaluate`` and the node load
(their model cards say how they were trained and what they score).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # not at run time: torch.hub.list would name them as entries
    from collections.abc import Callable
    from typing import Any

# torch.hub checks these import names before it loads an entry: what the entries import (scipy
# was listed too, which nothing imports, so torch.hub.load refused a setup without it).
dependencies = ['torch', 'numpy', 'numba', 'cv2']

_DEFAULT_MATCHER = 'census_bm'
_BASELINES = ('ccnn', 'lfn', 'lgcnet')


def _network(
    arch: str, matcher: str, max_disparity: int, pretrained: bool, device: str
) -> Any:
    import numpy as np

    from cva_confidence_ros.checks import is_int
    from cva_confidence_ros.errors import ConfigError
    from cva_confidence_ros.matching import MATCHERS
    from cva_confidence_ros.model import load_weights
    from cva_confidence_ros.model.hub import HubPredict
    from cva_confidence_ros.model.inference import resolve_device
    from cva_confidence_ros.model.weights import ARCHITECTURES, default_weights_path

    # An untrained network would take 64.7 as 64 and any matcher name into its meta.
    if not is_int(max_disparity) or max_disparity < 1:
        raise ConfigError(f'max_disparity must be an integer ≥ 1; got {max_disparity!r}')
    MATCHERS.get(matcher)
    # A truthy string ('False' from a config file) loaded the shipped weights.
    if not isinstance(pretrained, (bool, np.bool_)):
        raise ConfigError(f'pretrained must be True or False; got {pretrained!r}')
    if pretrained:
        path = default_weights_path(matcher, max_disparity, arch)
        net, meta = load_weights(path, matcher=matcher, max_disparity=max_disparity,
                                 device=device, arch=arch)
    else:
        meta = {'arch': arch, 'matcher': matcher, 'max_disparity': int(max_disparity)}
        net = ARCHITECTURES.get(arch)(meta)
        net.to(resolve_device(device)).eval()
    net.meta = meta
    # torch.hub.load takes the package off sys.path again; this keeps its inference at hand.
    # A class of the package, so that the network can still be pickled (torch.save).
    net.predict = HubPredict(net, arch in _BASELINES)
    return net


def cvanet(
    matcher: str = _DEFAULT_MATCHER, max_disparity: int = 64, pretrained: bool = True,
    device: str = 'cpu',
) -> Any:
    """CVA-Net, the paper's network (Mehltretter & Heipke 2019, Table 2), in eval mode.

    Args:
        matcher: The matcher whose cost volumes it judges: census_bm, census_sgm, mccnn_fast.
        max_disparity: Cost-volume depth D: 64 or 256 shipped (any D untrained).
        pretrained: Load the shipped weights (``models/cvanet_<matcher>_d<D>.pt``); False
            gives an untrained network, CVA-Net with the paper's initialisation (the other
            entries: that of their class).
        device: cpu, cuda or auto.

    Returns:
        The ``nn.Module``: input (B, 1, D, H + 12, W + 12), output (B, H, W) probabilities
        that the winner-takes-all disparity is correct; ``.meta`` what the weights are for,
        ``.predict(cost_volume)`` a whole (D, H, W) volume in memory-bounded tiles.
    """
    return _network('cvanet', matcher, max_disparity, pretrained, device)


def _entry(arch: str, doc: str) -> Callable[..., Any]:
    """A hub entry for ``arch`` with :func:`cvanet`'s options (torch.hub takes any callable
    not starting with ``_``; ``torch.hub.help`` shows ``doc``)."""

    def entry(
        matcher: str = _DEFAULT_MATCHER, max_disparity: int = 64, pretrained: bool = True,
        device: str = 'cpu',
    ) -> Any:
        return _network(arch, matcher, max_disparity, pretrained, device)

    entry.__name__ = entry.__qualname__ = arch
    entry.__doc__ = doc
    return entry


cvanet_fast = _entry('cvanet_fast', """CVA-Net-Fast, the network the node runs by default on a
    CPU (D = 64, 128, 256 shipped); otherwise as :func:`cvanet`.""")
cvanet_lite = _entry('cvanet_lite', """CVA-Net-Lite, the light network (D = 64 shipped);
    otherwise as :func:`cvanet`.""")
# The baselines' modules take other inputs than CVA-Net's (their help said "as cvanet").
ccnn = _entry('ccnn', """CCNN (Poggi & Mattoccia 2016), a baseline of the paper's Table 1,
    trained by this project (D = 64 shipped): it judges the disparity map,
    ``.predict(disparity, image)`` ((H, W) disparity in px, uint8 image → (H, W)). The
    module: ``net(disparity / D, grey / 255)``, each (B, 1, h + 8, w + 8) → (B, 1, h, w)
    probabilities (the image is ignored); options as :func:`cvanet`.""")
lfn = _entry('lfn', """LFN (Fu et al. 2017), a baseline of the paper's Table 1 (D = 64
    shipped): disparity and image, ``.predict(disparity, image)`` → (H, W). The module:
    ``net(disparity / D, grey / 255)``, each (B, 1, h + 8, w + 8) → (B, 1, h, w)
    probabilities; options as :func:`cvanet`.""")
lgcnet = _entry('lgcnet', """LGC-Net (Tosi et al. 2018), a baseline of the paper's Table 1
    (D = 64 shipped): disparity and image, ``.predict(disparity, image)`` → (H, W). The
    module: ``net(disparity / D, grey / 255)``, whole (B, 1, H, W) images → (B, 1, H, W)
    probabilities; options as :func:`cvanet`.""")


def pipeline(
    matcher: str = _DEFAULT_MATCHER, confidence_method: str = 'cva_net_fast', **options: Any
) -> Any:
    """The node's pipeline without ROS: rectified pair in; disparity, confidence and the kept
    pixels out (:class:`cva_confidence_ros.pipeline.StereoPipeline`).

    Args:
        matcher: census_bm, census_sgm or mccnn_fast.
        confidence_method: cva_net_fast (default), cva_net, cva_net_lite, ccnn, lfn, lgc_net,
            or a hand-crafted measure (pkrn, mlm, lrd, lrc, score).
        **options: Any other :class:`~cva_confidence_ros.pipeline.PipelineConfig` field
            (max_disparity, confidence_threshold, downsample, device, subpixel, ...).

    Returns:
        A ``StereoPipeline``; ``.process(left, right)`` gives a ``PipelineResult``.
    """
    from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline

    return StereoPipeline(
        PipelineConfig(matcher=matcher, confidence_method=confidence_method, **options)
    )
