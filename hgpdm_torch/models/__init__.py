"""Models: the GPDM, the hierarchical GPDM (H-GPDM) and the Intention-Driven Dynamics Model.

Saving and loading: :meth:`GPDM.save`, :func:`load_model`, :func:`register_model` for your own
subclasses, and :class:`ModelFileError` for files that cannot be loaded
(:mod:`~hgpdm_torch.models.persistence`).
"""

from .gpdm import GPDM
from .hgpdm import HGPDM, IDDM
from .persistence import ModelFileError, load_model, register_model, registered_models

__all__ = [
    "GPDM",
    "HGPDM",
    "IDDM",
    "ModelFileError",
    "load_model",
    "register_model",
    "registered_models",
]
