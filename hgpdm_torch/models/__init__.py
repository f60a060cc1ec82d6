"""Models: the GPDM, the hierarchical GPDM (H-GPDM) and the Intention-Driven Dynamics Model."""

from .gpdm import GPDM, load_model
from .hgpdm import HGPDM, IDDM

__all__ = ["GPDM", "HGPDM", "IDDM", "load_model"]
