"""Cross-validated choice of a :class:`~hgpdm_torch.models.LinearIDDM`'s belief options: the
noise kind and prior scales (``select="cv"``), the evidence temperature ``T`` and the forgetting
``eps`` (``"cv"``).

The evidence scores how well the model predicts the next frame, all ``Dz`` dimensions of it; the
beliefs need only the part of the dynamics that depends on ``g``, a few of the ``P Dz``
coefficients. ``select="cv"`` therefore chooses the noise kind and the prior scales by the
criterion of ``T`` and ``eps``: the likelihood of the true intentions under cross-validated beliefs
(jointly with ``T`` and ``eps`` where they are ``"cv"``). On the table-tennis strokes it picks a
3-30 times stronger ridge ``lambda`` than the evidence does and predicts the target better
(docs, target prediction). It costs a posterior per fold and candidate and the held-out
evidence of each (144 candidates with everything ``"auto"``: about 8 s for a hundred sequences
of 5 frames; each fold's held-out sequences are scored in one batch, padded to the longest).
"""

from __future__ import annotations

import math
import warnings
from typing import TYPE_CHECKING

import torch

from ..calibration import TEMPERATURE_BOUNDS, fit_temperature
from ..crossval import best_index, held_out, interleaved_folds
from .conjugate_regression import default_grid, posterior

if TYPE_CHECKING:
    from .linear_iddm import LinearIDDM

__all__ = ["FORGETTING_CANDIDATES", "BeliefSelection", "forgetful_sum"]

#: Candidates of ``forgetting="cv"``.
FORGETTING_CANDIDATES = (0.0, 0.1, 0.2, 0.3, 0.5, 0.7)


def forgetful_sum(steps: torch.Tensor, eps: float) -> torch.Tensor:
    """``B_t = (1 - eps) B_{t-1} + steps_t`` along dim -2 from ``B_0 = steps_0``:
    ``[..., T, K] -> [..., T, K]`` (a cumulative sum for ``eps = 0``)."""
    if eps == 0.0:
        return steps.cumsum(-2)
    out = [steps[..., 0, :]]
    for t in range(1, steps.shape[-2]):
        out.append((1.0 - eps) * out[-1] + steps[..., t, :])
    return torch.stack(out, -2)


class BeliefSelection:
    """The cross-validation of :class:`~hgpdm_torch.models.LinearIDDM`'s ``"cv"`` options, a base
    of the model (it uses the model's design, posterior assignment and transition evidence on
    each fold's sub-model, ``_fold_model``)."""

    def _cross_validate(
        self: LinearIDDM, seqs: list[torch.Tensor], g: torch.Tensor, num_values: int | None,
        candidates: list[tuple[str, tuple[float, float]]],
    ) -> tuple[str, tuple[float, float], float, float]:  # fmt: skip
        """The candidate ``(noise kind, (lambda, psi))`` and ``(T, eps)`` whose beliefs of each
        held-out sequence, by the candidate fitted on the other folds (every frame after the
        first; the truth is the nearest grid value), give the truths the smallest mean negative
        log probability: for each candidate and each candidate ``eps``, ``T`` by
        :func:`~hgpdm_torch.calibration.fit_temperature` (or the given ``T``; the
        given ``eps``). Ties go to the earlier candidate."""

        folds = min(self.cv_folds, len(seqs))  # >= 2: fit refuses a single intention value
        # the fitted model's default grid; the distinct training intentions for a 2-D+ g
        if g.shape[1] > 1:
            values = torch.unique(g, dim=0)
        else:
            values = default_grid(g, self.intention, num_values, 25)
        truth = torch.cdist(g, values).argmin(-1)
        # per fold: its design, its held-out sequences [n, T, Dz] and the mask of their
        # transitions, and the true value index of each transition
        # held-out training frames are scored whatever their distance from the other folds'
        sub = self._fold_model(num_values)

        def prepare(k: int, rest: list[int], held: list[int]) -> tuple:
            """Fold ``k``'s design, held-out batch, transition mask and true value indices."""
            with warnings.catch_warnings():  # few transitions per phase: the full fit warned
                warnings.simplefilter("ignore")
                design = sub._design([seqs[j] for j in rest], g[rest], num_values)
            cut = len(design.parts) + 1 if self.phase else None
            held_seqs = [seqs[j][:cut] for j in held]
            # one batch: each sequence padded with its last frame to the longest, and a mask
            # [n, T - 1] of its own transitions (the padding's evidence is never scored)
            longest = max(len(q) for q in held_seqs)
            batch = torch.stack([torch.cat([q, q[-1:].expand(longest - len(q), -1)])
                                 for q in held_seqs])  # fmt: skip
            steps_idx = torch.arange(longest - 1, device=batch.device)
            lengths = torch.tensor([len(q) for q in held_seqs], device=batch.device)
            mask = steps_idx < (lengths[:, None] - 1)
            return (design, rest, batch, mask), truth[held][:, None].expand_as(mask)[mask]

        prepared = held_out(interleaved_folds(len(seqs), folds), prepare)
        splits = [split for split, _ in prepared]
        hits = [hit for _, hit in prepared]
        hits_all = torch.cat(hits)
        epsilons = (FORGETTING_CANDIDATES if self._forgetting_arg == "cv"
                    else (self._forgetting_arg,))  # fmt: skip
        posteriors: dict[tuple[int, tuple[float, float]], list] = {}  # per (fold, prior)
        tried, losses = [], []  # (kind, prior, temperature, eps) and its held-out NLL
        for kind, prior in candidates:  # one candidate's held-out evidence in memory at a time
            steps = []  # per fold: [n, T - 1, K] evidence of each held-out transition, mask
            for fold, (design, rest, batch, mask) in enumerate(splits):
                if (fold, prior) not in posteriors:
                    posteriors[fold, prior] = [posterior(u, y, *prior) for u, y in design.parts]
                sub._assign(design, g[rest], num_values, kind, prior, posteriors[fold, prior],
                            math.nan)  # fmt: skip
                steps.append((sub._transition_evidence(batch, values)[:, 1:], mask))
            for eps in epsilons:
                # from a uniform prior B_0 = 0, B_t is the forgetful sum of the first t steps
                # (a padded step comes after all of a sequence's own: it changes none of them)
                logs = torch.cat([forgetful_sum(e, float(eps))[m] for e, m in steps])
                if self._temperature_arg == "cv":
                    temperature = fit_temperature(logs, hits_all)
                else:
                    temperature = self._temperature_arg
                log_p = torch.log_softmax(logs / temperature, -1)
                losses.append(-float(log_p.gather(-1, hits_all[:, None]).mean()))
                tried.append((kind, prior, temperature, float(eps)))
        kind, prior, temperature, eps = tried[best_index(losses)]
        if self._temperature_arg == "cv" and not (
            1.01 * TEMPERATURE_BOUNDS[0] < temperature < TEMPERATURE_BOUNDS[1] / 1.01
        ):
            warnings.warn(
                f"LinearIDDM: the cross-validated temperature is at its bound ({temperature:.3g}"
                "): the held-out beliefs are " + ("never wrong (separable data: the beliefs "
                "become one-hot)" if temperature < 1 else "uninformative about g") + "; pass a "
                "temperature to choose it yourself",
                stacklevel=3,
            )  # fmt: skip
        if len(epsilons) > 1 and eps == epsilons[-1]:
            warnings.warn(
                f"LinearIDDM: the cross-validation chose forgetting = {eps:g}, the edge of its "
                f"candidates; pass a value to go beyond it",
                stacklevel=3,
            )
        return kind, prior, temperature, eps
