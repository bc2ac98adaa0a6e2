"""Learned feature networks (DPCN++, DESIGN 3): MONAI UNets around the differentiable solver, and their weights."""

from dpcn_med.models.dpcn import DPCN, DPCNOutput, ModelConfig, pose_loss
from dpcn_med.models.features import FeatureExtractor
from dpcn_med.models.weights import load_model, model_paths, save_model

__all__ = ["DPCN", "DPCNOutput", "FeatureExtractor", "ModelConfig", "load_model", "model_paths", "pose_loss",
           "save_model"]
