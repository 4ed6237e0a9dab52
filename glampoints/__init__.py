"""GLAMpoints (Truong et al., ICCV 2019): a learned keypoint detector for retinal images.

Public API: the detector (`GlamPoints`, `Keypoints`, `WeightsError`), the network (`UNet`),
NMS, the upright root-SIFT descriptor and the paper's metrics. Training lives in
`glampoints.training` (imported on demand: it pulls in tqdm and the data pipeline).
"""

from importlib import import_module
from typing import TYPE_CHECKING, Any

# Loaded on first use (PEP 562): importing the package must not import torch, so that the
# `glampoints` command can catch Ctrl-C while torch loads (seconds) and exit without a traceback.
_HOME = {
    "rootsift": "descriptors",
    "upright_rootsift": "descriptors",
    "DEFAULT_WEIGHTS": "detector",
    "GlamPoints": "detector",
    "Keypoints": "detector",
    "WeightsError": "detector",
    "fold_batchnorm": "detector",
    "load_weights": "detector",
    "save_weights": "detector",
    "failure_reason": "metrics",
    "matching_score": "metrics",
    "registration_class": "metrics",
    "repeatability": "metrics",
    "six_fixed_points": "metrics",
    "true_positive_mask": "metrics",
    "warp_points": "metrics",
    "nms": "nms",
    "nms_numpy": "nms",
    "UNet": "unet",
}

if TYPE_CHECKING:
    from glampoints.descriptors import rootsift, upright_rootsift
    from glampoints.detector import (
        DEFAULT_WEIGHTS,
        GlamPoints,
        Keypoints,
        WeightsError,
        fold_batchnorm,
        load_weights,
        save_weights,
    )
    from glampoints.metrics import (
        failure_reason,
        matching_score,
        registration_class,
        repeatability,
        six_fixed_points,
        true_positive_mask,
        warp_points,
    )
    from glampoints.nms import nms, nms_numpy
    from glampoints.unet import UNet


def __getattr__(name: str) -> Any:
    if name not in _HOME:
        raise AttributeError(f"module 'glampoints' has no attribute {name!r}")
    value = getattr(import_module(f"glampoints.{_HOME[name]}"), name)
    globals()[name] = value
    return value


__all__ = [
    "DEFAULT_WEIGHTS",
    "GlamPoints",
    "Keypoints",
    "UNet",
    "WeightsError",
    "failure_reason",
    "fold_batchnorm",
    "load_weights",
    "matching_score",
    "nms",
    "nms_numpy",
    "registration_class",
    "repeatability",
    "rootsift",
    "save_weights",
    "six_fixed_points",
    "true_positive_mask",
    "upright_rootsift",
    "warp_points",
]
