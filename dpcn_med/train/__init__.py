"""Training the DPCN++ feature networks: configs, data, the loop (single device or DistributedDataParallel)."""

from dpcn_med.train.config import DataConfig, OptimiserConfig, TrainConfig, load_config
from dpcn_med.train.loop import train

__all__ = ["DataConfig", "OptimiserConfig", "TrainConfig", "load_config", "train"]
