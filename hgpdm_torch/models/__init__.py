"""Models: the GPDM, the hierarchical GPDM (H-GPDM), the Intention-Driven Dynamics Model and its
linear-Gaussian, phase-indexed counterpart :class:`LinearIDDM`.

Saving and loading: :meth:`GPDM.save`, :func:`load_model` (``model=``: into a model your code
built, e.g. with a custom kernel), :func:`register_model` for your own subclasses, and
:class:`ModelFileError` for files that cannot be loaded (:mod:`~hgpdm_torch.models.persistence`).
:func:`supervised_init`: initial latent states that covary with the intention (partial least
squares), for ``init``. :class:`MAPObjective` (``model.objective()``): the negative log posterior
of Eq. 6 beside a GP model; :func:`~hgpdm_torch.models.objective.fit` fits a model to it with
any optimizer (:mod:`~hgpdm_torch.models.objective`).
"""

from .gpdm import GPDM
from .hgpdm import HGPDM, IDDM
from .latent_init import supervised_init
from .linear_iddm import LinearIDDM
from .objective import MAPObjective
from .persistence import ModelFileError, load_model, register_model, registered_models

# the built-in classes; persistence imports no model, so that each model module can import it
for _cls in (GPDM, HGPDM, IDDM, LinearIDDM):
    register_model(_cls)
del _cls

__all__ = [
    "GPDM",
    "HGPDM",
    "IDDM",
    "LinearIDDM",
    "MAPObjective",
    "ModelFileError",
    "load_model",
    "register_model",
    "registered_models",
    "supervised_init",
]
