"""GLAMpoints (Truong et al., ICCV 2019): a learned keypoint detector for retinal images.

Public API: the detector (`GlamPoints`, `Keypoints`, `WeightsError`), the network (`UNet`),
NMS, the upright root-SIFT descriptor and the paper's metrics. Training lives in
`glampoints.training` (imported on demand: it pulls in tqdm and the data pipeline).
"""

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
