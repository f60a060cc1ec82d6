"""hgpdm-torch: intention inference and decision making with Hierarchical GP Dynamics Models.

The public API, re-exported. Subpackages: :mod:`hgpdm_torch.models`, :mod:`hgpdm_torch.inference`,
:mod:`hgpdm_torch.decision`, :mod:`hgpdm_torch.datasets`, :mod:`hgpdm_torch.experiments` and
:mod:`hgpdm_torch.robots` (the SAPIEN scene; imported on demand because it needs the ``sim``
extra).

Every name is imported on first use (PEP 562), so ``import hgpdm_torch`` -- and with it the
``hgpdm`` command's ``--help`` -- does not load torch, gpytorch or pyro. ``hgpdm_torch.HGPDM`` and
``from hgpdm_torch import HGPDM`` work as usual.
"""

from __future__ import annotations

from ._lazy import lazy_exports

__version__ = "0.1.0"

# public name -> module it lives in (relative to this package); a subpackage maps to itself.
# New exports go here (and nowhere else: an eager import would load torch for ``hgpdm --help``).
_EXPORTS: dict[str, str] = {
    "ALPHA_BAR": ".kernels",
    "CVResult": ".model_selection",
    "CholeskyError": ".linalg",
    "GPDM": ".models",
    "GPPosterior": ".gp",
    "HGPDM": ".models",
    "IDDM": ".models",
    "LinearIDDM": ".models",
    "ModelFileError": ".models",
    "OnlineIntentionFilter": ".inference.intention",
    "cross_validate": ".model_selection",
    "datasets": ".datasets",
    "decision": ".decision",
    "expectations": ".expectations",
    "inference": ".inference",
    "kernels": ".kernels",
    "load_model": ".models",
    "measurement_kernel": ".kernels",
    "models": ".models",
    "settings": ".settings",
    "transition_kernel": ".kernels",
}

__all__ = sorted(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
