"""Arrays on the host for the code that runs without torch (the tracking process, :mod:`services.ba.core.se3_numpy`,
:mod:`services.ba.core.projective_numpy`): mapping hands it torch tensors, tracking numpy arrays, and neither
side should need the other's library to do so."""
from __future__ import annotations

import numpy as np


def as_numpy(x, dtype=np.float64) -> np.ndarray:
    """``x`` (a torch tensor on any device, or anything numpy takes) as a numpy array of ``dtype`` (None: keep
    its own). A tensor is recognised by its ``detach``, so that this module never imports torch."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x) if dtype is None else np.asarray(x, dtype=dtype)
