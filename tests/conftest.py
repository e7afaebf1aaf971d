"""Shared test settings: CPU, no network, deterministic threads."""
import os
import warnings

os.environ.setdefault("WANDB_MODE", "disabled")
os.environ.setdefault("HYDRA_FULL_ERROR", "1")
warnings.filterwarnings("ignore", message=".*settotalmass.*")

import torch

torch.set_num_threads(1)
