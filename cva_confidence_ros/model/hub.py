"""``net.predict`` of the networks that ``hubconf.py`` hands out through ``torch.hub``.

It lives in the package, not in ``hubconf.py``: ``torch.hub`` imports that file under the
module name ``hubconf.py``, which no one can import again, so a network carrying a helper
defined there could not be pickled (``torch.save(net, ...)``, ``copy`` through pickle, or
sending it to a worker process).
"""

from __future__ import annotations

import inspect
from typing import Any

__all__ = ['HubPredict']


class HubPredict:
    """``net.predict(...)`` on the network's device: for the CVA-Net family
    ``predict(cost_volume, **options)`` (:func:`cva_confidence_ros.model.predict_confidence`:
    a whole (D, H, W) volume in memory-bounded tiles); for CCNN, LFN and LGC-Net
    ``predict(disparity, image)``
    (:func:`cva_confidence_ros.model.baselines.predict_disparity_confidence`).

    Args:
        net: The network it runs.
        baseline: Whether ``net`` is a baseline that reads a disparity map and an image.
    """

    def __init__(self, net: Any, baseline: bool) -> None:
        self._net = [net]  # a list: not registered as a submodule of the network
        self._baseline = baseline

    def __call__(self, *args: Any, **options: Any) -> Any:
        from cva_confidence_ros.model import predict_confidence
        from cva_confidence_ros.model.baselines import predict_disparity_confidence

        net = self._net[0]
        run = predict_disparity_confidence if self._baseline else predict_confidence
        # A device given by position (predict(volume, 'cpu')) is one too: a default added as a
        # keyword beside it was a TypeError ('got multiple values for argument device').
        if 'device' not in inspect.signature(run).bind_partial(net, *args, **options).arguments:
            options['device'] = next(net.parameters()).device
        return run(net, *args, **options)
