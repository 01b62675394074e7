"""Stereo data sets with ground truth, in the package's array conventions.

``load_scene('middlebury2014', '/data/MiddEval3', 'Motorcycle')`` returns a
:class:`StereoSample`; :func:`fit_disparity_range` shrinks it until its disparities fit into
the cost-volume depth. :data:`TRAIN_DATASETS` and :data:`DEVELOP_DATASETS` keep the train /
develop split of the project (never train on a develop set).
"""

from __future__ import annotations

from cva_confidence_ros.datasets import io
from cva_confidence_ros.datasets.io import Calibration, read_pfm, write_pfm
from cva_confidence_ros.datasets.loaders import (
    DATASETS,
    DEVELOP_DATASETS,
    TRAIN_DATASETS,
    StereoDataset,
    StereoSample,
    list_scenes,
    load_dataset,
    load_scene,
    skipped_notice,
    skipped_scenes,
)
from cva_confidence_ros.datasets.resize import (
    fit_disparity_range,
    resize_disparity,
    resize_sample,
)

__all__ = [
    'DATASETS',
    'DEVELOP_DATASETS',
    'TRAIN_DATASETS',
    'Calibration',
    'StereoDataset',
    'StereoSample',
    'fit_disparity_range',
    'io',
    'list_scenes',
    'load_dataset',
    'load_scene',
    'read_pfm',
    'resize_disparity',
    'resize_sample',
    'skipped_notice',
    'skipped_scenes',
    'write_pfm',
]
