"""hgpdm-torch: intention inference and decision making with Hierarchical GP Dynamics Models.

The public API, re-exported. Subpackages: :mod:`hgpdm_torch.models`, :mod:`hgpdm_torch.inference`,
:mod:`hgpdm_torch.decision`, :mod:`hgpdm_torch.datasets`, :mod:`hgpdm_torch.experiments` and
:mod:`hgpdm_torch.robots` (the SAPIEN scene; imported on demand because it needs the ``sim``
extra).
"""

from . import datasets, decision, expectations, inference, kernels, models
from .gp import GPPosterior
from .kernels import ALPHA_BAR, measurement_kernel, transition_kernel
from .linalg import CholeskyError
from .model_selection import CVResult, cross_validate
from .models import GPDM, HGPDM, IDDM, load_model

__version__ = "0.1.0"

__all__ = [
    "ALPHA_BAR",
    "CVResult",
    "CholeskyError",
    "GPDM",
    "GPPosterior",
    "HGPDM",
    "IDDM",
    "cross_validate",
    "datasets",
    "decision",
    "expectations",
    "inference",
    "kernels",
    "load_model",
    "measurement_kernel",
    "models",
    "transition_kernel",
]
