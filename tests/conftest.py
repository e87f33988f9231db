import os
import sys

import torch

sys.path.insert(0, os.path.dirname(__file__))  # tests import reference.py / random_scenes.py as modules
torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))


def as_float32(scene):
    """The float64 scene dict converted to float32 tensors for the Warp renderer."""
    return {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
