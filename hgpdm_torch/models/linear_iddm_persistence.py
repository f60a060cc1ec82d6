"""Persistence of a fitted :class:`~hgpdm_torch.models.LinearIDDM`: its configuration, training data
and fitted statistics in the checksummed, versioned format of
:mod:`~hgpdm_torch.models.persistence`, and the checks that rebuild it from a file (the
statistics must be those its own data give).
"""

from __future__ import annotations

import warnings
from typing import Any

import torch

from .persistence import SavedModel, save_model

__all__ = ["LinearIDDMPersistence"]


class LinearIDDMPersistence(SavedModel):
    """The :class:`~hgpdm_torch.models.persistence.SavedModel` side of
    :class:`~hgpdm_torch.models.LinearIDDM`, a base of the model."""

    #: the fitted statistics :meth:`state_dict` holds
    _STATE = (
        "obs_mean", "obs_std", "intentions", "directions", "precision", "coef", "scatter", "dof",
    )  # fmt: skip

    def config(self) -> dict[str, Any]:
        """Constructor arguments that refit this model without any search: the noise kind,
        prior, temperature and forgetting as chosen (not ``"auto"``/``"cv"``)."""
        self._check_fitted()
        return {"intention": self.intention, "num_values": self._num_values_arg,
                "phase": self.phase, "noise": self.noise_kind,
                "coef_precision": self.prior[0], "noise_prior": self.prior[1],
                "interaction_rank": self.interaction_rank, "temperature": self.temperature,
                "forgetting": self.forgetting, "cv_folds": self.cv_folds,
                "outlier_sd": self.outlier_sd}  # fmt: skip

    def _data_arguments(self) -> dict[str, Any]:
        """:meth:`fit`'s arguments: the training ``sequences`` and their ``intentions``."""
        self._check_fitted()
        g = self.intentions[:, 0] if self.intention_dim == 1 else self.intentions
        if self.intention == "discrete":
            g = g.long()
        return {"sequences": [s.clone() for s in self._sequences], "intentions": g.clone()}

    def state_dict(self) -> dict[str, torch.Tensor]:
        """The fitted statistics (standardisation, training intentions and each phase's
        interaction directions ``V_s``, ``Lambda_n``, ``M_n``, ``Psi_n``, ``nu_n``) and the
        evidence, as tensors."""
        self._check_fitted()
        state = {k: getattr(self, k).clone() for k in self._STATE}
        state["log_evidence"] = torch.tensor(self._evidence, dtype=self.dtype)
        return state

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Take saved statistics into this fitted model; each must agree with what its own
        training data give, to ``1e-6`` (float64) or ``1e-3`` (float32) of the tensor's largest
        entry (at least 1): another machine's summation order moves them by far less (measured
        up to ``1e-9`` / ``3e-6``), statistics of other data by far more.

        Raises:
            RuntimeError: other keys, shapes or dtypes, or statistics of other data.
        """
        own = self.state_dict()
        if "directions" not in state and own["directions"].shape[-1] == 0:
            state = {**state, "directions": own["directions"]}  # files from before the option
        if set(state) != set(own):
            raise RuntimeError(f"state keys {sorted(state)} differ from {sorted(own)}")
        for key, mine in own.items():
            theirs = state[key]
            if not isinstance(theirs, torch.Tensor) or (theirs.shape, theirs.dtype) != (
                mine.shape, mine.dtype
            ):  # fmt: skip
                raise RuntimeError(f"state[{key!r}] must be a {mine.dtype} tensor {mine.shape}")
            tol = 1e-6 if self.dtype == torch.float64 else 1e-3
            scale = float(mine.abs().max().clamp_min(1.0)) if mine.numel() else 1.0
            if mine.numel() and float((theirs.to(mine.device) - mine).abs().max()) > tol * scale:
                raise RuntimeError(
                    f"state[{key!r}] differs from what the training data give: the statistics "
                    "belong to other data"
                )
        for key in self._STATE:
            setattr(self, key, state[key].to(own[key].device).clone())
        self._evidence = float(state["log_evidence"])
        self.precision_tril = torch.linalg.cholesky(self.precision)

    @classmethod
    def _from_saved(
        cls, data: dict[str, Any], config: dict[str, Any], dtype: torch.dtype,
        state: dict[str, Any],
    ) -> Any:  # fmt: skip
        """The model :func:`~hgpdm_torch.models.load_model` rebuilds from a file: constructed
        from ``config`` and fitted on ``data``. ``config`` must hold the choices (no
        ``"auto"``/``"cv"`` search), and the saved coefficients' shape must be the one the
        data and ``config`` imply before anything is fitted, so a file cannot ask for more work
        than its own size.

        Raises:
            ValueError: a search in ``config``, or statistics of another shape.
        """
        searched = [k for k in ("noise", "coef_precision", "noise_prior", "temperature",
                                "forgetting") if config.get(k) in ("auto", "cv")]  # fmt: skip
        if searched:
            raise ValueError(f"the configuration asks for a search ({', '.join(searched)})")
        seqs, g = data.get("sequences"), data.get("intentions")
        coef = state.get("coef")
        if not (isinstance(seqs, list) and seqs and isinstance(g, torch.Tensor)
                and isinstance(coef, torch.Tensor) and coef.dim() == 3):  # fmt: skip
            raise ValueError("the data need sequences, intentions and [S, P, Dz] coefficients")
        if config.get("intention") == "discrete":
            width = config.get("num_values") or int(g.max()) + 1
        else:
            width = 1 if g.dim() == 1 else g.shape[-1]
        dz = seqs[0].shape[-1] if isinstance(seqs[0], torch.Tensor) else -1
        phases = max(len(q) for q in seqs) - 1 if config.get("phase", True) else 1
        rank = config.get("interaction_rank", 0)
        size = dz + width + 1 + width * rank if isinstance(rank, int) else -1
        if tuple(coef.shape) != (phases, size, dz):
            raise ValueError(
                f"the saved coefficients {tuple(coef.shape)} do not fit the data "
                f"({phases}, {size}, {dz})"
            )
        with warnings.catch_warnings():  # the original fit warned already
            warnings.simplefilter("ignore")
            return cls(**config, dtype=dtype).fit(**data)

    def save(self, path: Any) -> None:
        """Save the fitted model to ``path`` in the checksummed, versioned format of
        :mod:`~hgpdm_torch.models.persistence` (configuration, training data, statistics);
        load it with :func:`~hgpdm_torch.models.load_model` or :meth:`load`. A registered
        subclass's own plain constructor arguments are saved with the configuration.

        Raises:
            RuntimeError: the model is not fitted.
            TypeError: its class is not registered (:func:`~hgpdm_torch.models.register_model`).
        """
        self._check_fitted()
        save_model(self, path)

    def _saved_dtype(self) -> torch.dtype:
        return self.dtype
