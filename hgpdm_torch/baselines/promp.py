"""Probabilistic movement primitives (ProMP) conditioned on a movement's prefix, with its phase
estimated: the baseline of the interaction-primitive literature.

A ProMP represents each training movement ``y [T_i, D]`` by the weights of normalised radial
basis functions over its phase ``s = j / (T_i - 1)`` (``y_j = (I_D kron phi(s_j))^T w + eps``),
and the movements by a Gaussian over those weights, joint with any per-movement quantities
``e`` (a table-tennis target; interaction primitives augment the weights with the partner's
variables the same way): ``[w, e] ~ N(m, S)``. A prefix of ``t`` frames of a new movement is
conditioned on for every candidate duration ``T_c`` (the phase is unknown: how fast the
movement runs is estimated from the prefix, as in phase estimation for action recognition):

- evidence ``p(Y | T_c) = N(Y | H_c m_w, H_c S_ww H_c^T + R)``, ``H_c`` the basis at the
  prefix's phases ``j / (T_c - 1)`` (clipped to 1: past its end a movement holds its last
  posture), ``R`` the per-channel noise of the training fits;
- the posterior ``[w, e] | Y, T_c`` in information form, ``P_c = S^-1 + H_c^T R^-1 H_c``, whose
  size ``D B + E`` does not grow with the prefix, and ``P_c`` is shared by all streams of a
  batch at the same prefix length;
- the candidates mixed by their evidence (a uniform prior over them), the mixture of the
  ``e`` posteriors matched by its mean and covariance.

Library: the basis functions are mp_pytorch's (``NormalizedRBFBasisGenerator`` over a
``LinearPhaseGenerator``): torch-native, so the baseline runs in the toolkit's dtype and device
and batches over candidates and streams; ALR's ``fancy_gym`` table-tennis environments build on
it. Conditioning on a multi-frame prefix, the phase estimation and the augmented weights are
this module's: mp_pytorch has none of them. ``movement_primitives``' ProMP (NumPy) conditions on
one via-point at a time, has no phase estimation and no per-movement quantities (a target must
ride along as a constant channel). Measured on the target-prediction strokes (``python -m
benchmarks promp_libraries``, 4 basis functions per channel, 126 test strokes): this module
errs 50.9 / 51.0 / 43.6 / 34.2 cm at 320 / 240 / 160 / 80 ms before the hit, against 44.7 /
47.0 / 40.1 / 39.8 for ``movement_primitives`` (SEM 2.5-3.1: it is ahead 320-160 ms before the
hit, this module at 80 ms), and
with 6 basis functions 51.1 / 46.9 / 46.8 / 34.0 against 48.0 / 51.9 / 56.9 / 51.6; it fits 16-32x
and decides 9-18x faster (0.01 against 0.11-0.16 ms per decision).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import torch

from ..validation import as_tensor
from .windows import as_sequences, check_fitted, positive_int

__all__ = [
    "PROMP_CLASS_GRID",
    "PROMP_GRID",
    "PrefixPosterior",
    "ProMP",
    "ProMPClassifier",
    "ProMPRegressor",
]


class PrefixPosterior(NamedTuple):
    """What a prefix tells, per stream ``[B]``.

    Attributes:
        log_evidence: ``log p(Y) [B]``, the prefix's log likelihood, mixed over the durations.
        mean: ``E[e | Y] [B, E]`` of the per-movement quantities fitted jointly.
        cov: ``Cov[e | Y] [B, E, E]`` (the mixture over durations, matched by its moments).
        duration_weights: ``p(T_c | Y) [B, C]`` over :attr:`ProMP.durations`.
    """

    log_evidence: torch.Tensor
    mean: torch.Tensor
    cov: torch.Tensor
    duration_weights: torch.Tensor


def _basis(num_basis: int, bandwidth: float, phases: torch.Tensor) -> torch.Tensor:
    """mp_pytorch's normalised RBF basis ``[..., t, num_basis]`` at ``phases [..., t]`` (in
    ``[0, 1]``; larger values are clipped to 1)."""
    from mp_pytorch.basis_gn import NormalizedRBFBasisGenerator  # heavy: imports matplotlib
    from mp_pytorch.phase_gn import LinearPhaseGenerator

    kw = {"dtype": phases.dtype, "device": phases.device}
    gen = NormalizedRBFBasisGenerator(
        LinearPhaseGenerator(tau=1.0, **kw), num_basis=num_basis,
        basis_bandwidth_factor=bandwidth, **kw,
    )  # fmt: skip
    return gen.basis(phases)


class ProMP:
    """A ProMP over ``D`` channels, optionally joint with ``E`` per-movement quantities.

    Args:
        num_basis: basis functions per channel ``B``.
        speeds: relative speeds tried for a prefix: the candidate durations are the training
            durations' quantiles (``durations`` of them) over each speed (``(1.0,)``: the
            training durations only).
        durations: number of quantiles of the training durations among the candidates
            (fewer where the training durations take fewer values).
        bandwidth: mp_pytorch's ``basis_bandwidth_factor`` (width of the basis functions
            against their spacing).
        reg: ridge of each movement's weight fit, relative to the basis's Gram matrix scale.

    Attributes (after :meth:`fit`):
        mean ``[D B + E]``, cov ``[D B + E, D B + E]``: the Gaussian over weights and extras
        (scikit-learn's Ledoit-Wolf shrinkage of the standardised training weights, plus 1e-6
        of their unit variance: well conditioned with fewer movements than weights);
        noise ``[D]``: each channel's residual variance of the weight fits;
        durations ``[C]``: the candidate durations [frames].
    """

    def __init__(
        self,
        num_basis: int = 6,
        *,
        speeds: Sequence[float] = (1.0,),
        durations: int = 5,
        bandwidth: float = 3.0,
        reg: float = 1e-6,
    ) -> None:
        self.num_basis = positive_int(num_basis, "num_basis")
        self.num_durations = positive_int(durations, "durations")
        speeds = tuple(float(s) for s in speeds)
        if not speeds or not all(math.isfinite(s) and s > 0 for s in speeds):
            raise ValueError(f"speeds must be positive finite numbers, got {speeds!r}")
        if not (math.isfinite(bandwidth) and bandwidth > 0):
            raise ValueError(f"bandwidth must be a positive number, got {bandwidth!r}")
        if not (math.isfinite(reg) and reg >= 0):
            raise ValueError(f"reg must be a non-negative number, got {reg!r}")
        self.speeds, self.bandwidth, self.reg = speeds, float(bandwidth), float(reg)

    # -- fitting ---------------------------------------------------------------------------
    def basis(self, frames: int, duration: torch.Tensor) -> torch.Tensor:
        """The basis ``[C, frames, B]`` at frames ``0..frames-1`` of movements lasting
        ``duration [C]`` frames (phase ``j / (T_c - 1)``)."""
        j = torch.arange(frames, dtype=duration.dtype, device=duration.device)
        return _basis(self.num_basis, self.bandwidth, j / (duration[:, None] - 1).clamp_min(1))

    def _weights(self, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Ridge weights ``[D B]`` of one movement ``y [T, D]`` and its squared residuals
        ``[D]`` summed over frames."""
        phi = self.basis(y.shape[0], y.new_tensor([y.shape[0]]))[0]  # [T, B]
        gram = phi.T @ phi
        gram = gram + self.reg * gram.diagonal().mean() * torch.eye(self.num_basis).to(gram)
        w = torch.linalg.solve(gram, phi.T @ y)  # [B, D]
        return w.T.reshape(-1), (y - phi @ w).pow(2).sum(0)

    def fit(self, sequences: Any, extras: Any = None) -> ProMP:
        """Fit to movements ``[T_i, D]`` (``T_i >= 2``), with their ``extras [n, E]`` if any.

        Raises:
            ValueError: fewer than 2 movements, a movement of one frame, non-finite values or
                ``extras`` with another number of rows.
        """
        from sklearn.covariance import LedoitWolf

        seqs = as_sequences(sequences)
        if len(seqs) < 2:
            raise ValueError(f"sequences: a ProMP needs at least 2 movements, got {len(seqs)}")
        short = [i for i, s in enumerate(seqs) if s.shape[0] < 2]
        if short:
            raise ValueError(f"sequences: movements {short} have fewer than 2 frames")
        seqs = [s.to(torch.float64) for s in seqs]
        if extras is None:
            e = seqs[0].new_zeros(len(seqs), 0)
        else:
            e = as_tensor(extras, "extras", dtype=torch.float64, min_ndim=1)
            e = e[:, None] if e.dim() == 1 else e
            if e.dim() != 2 or e.shape[0] != len(seqs):
                raise ValueError(
                    f"extras must be [n, E] with one row per movement (n = {len(seqs)}), "
                    f"got {tuple(e.shape)}"
                )
        self.dim, self.num_extras = seqs[0].shape[1], e.shape[1]
        fits = [self._weights(s) for s in seqs]
        z = torch.cat([torch.stack([w for w, _ in fits]), e], 1)  # [n, D B + E]
        frames = sum(s.shape[0] for s in seqs)
        variance = torch.cat(seqs).var(0)
        # residual variance per channel, floored at 1e-6 of the channel's variance so that a
        # channel the basis fits exactly does not make every other candidate impossible
        self.noise = (sum(r for _, r in fits) / frames).clamp_min(1e-6 * variance.clamp_min(1e-12))
        loc, scale = z.mean(0), z.std(0)
        scale = scale.clamp_min(1e-9 * float(scale.max()) + 1e-300)  # a constant coordinate
        shrunk = torch.as_tensor(LedoitWolf().fit(((z - loc) / scale).numpy()).covariance_)
        # Ledoit-Wolf may not shrink at all (two movements: a rank-1 estimate); 1e-6 of the
        # unit variances keeps the condition number below ~1e6 (D B + E)
        shrunk = shrunk + 1e-6 * torch.eye(len(loc), dtype=shrunk.dtype)
        self.mean = loc
        self.cov = shrunk * scale[:, None] * scale[None, :]
        self.cov_chol = torch.linalg.cholesky(self.cov)
        self.precision = torch.cholesky_inverse(self.cov_chol)
        length = torch.tensor([float(s.shape[0]) for s in seqs], dtype=torch.float64)
        q = torch.linspace(0, 1, self.num_durations + 2, dtype=torch.float64)[1:-1]
        base = torch.unique(torch.quantile(length, q).round())
        speeds = torch.tensor(self.speeds, dtype=torch.float64)
        self.durations = torch.unique((base[:, None] / speeds[None, :]).round().clamp_min(2))
        return self

    # -- conditioning ----------------------------------------------------------------------
    def _checked(self, prefix: Any) -> torch.Tensor:
        check_fitted(self, "mean", "fit(sequences)")
        y = as_tensor(prefix, "prefix", dtype=torch.float64)
        if y.dim() != 3 or y.shape[2] != self.dim:
            raise ValueError(f"prefix must be [B, t, D = {self.dim}], got {tuple(y.shape)}")
        return y

    def _per_duration(self, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """For each candidate duration: the log evidence with the prior over candidates ``[B,
        C]``, the posterior mean of ``[w, e]`` ``[B, C, M]`` and the Cholesky factor of its
        precision ``P_c`` ``[C, M, M]`` given ``y [B, t >= 1, D]``."""
        b, t, d = y.shape
        n_w, nb, C = d * self.num_basis, self.num_basis, len(self.durations)
        phi = self.basis(t, self.durations)  # [C, t, B]
        # P_c = S^-1 + H_c^T R^-1 H_c: H_c is block diagonal (one block phi_c per channel)
        gram = phi.mT @ phi  # [C, B, B]
        info = y.new_zeros(C, n_w + self.num_extras, n_w + self.num_extras)
        for k in range(d):
            block = slice(k * nb, (k + 1) * nb)
            info[:, block, block] = gram / self.noise[k]
        chol = torch.linalg.cholesky(self.precision + info)  # [C, M, M]
        # residuals r = Y - H_c m_w and u = H_c^T R^-1 r (zero for the extras)
        m_w = self.mean[:n_w].view(d, nb)
        r = y[:, None] - torch.einsum("ctj,dj->ctd", phi, m_w)  # [B, C, t, D]
        r = r / self.noise
        u = torch.einsum("ctj,bctd->bcdj", phi, r).reshape(b, C, n_w)
        u = torch.cat([u, u.new_zeros(b, C, self.num_extras)], -1)
        # P_c^-1 u: [B, C, M], the streams as right-hand sides of one solve per candidate
        sol = torch.cholesky_solve(u.permute(1, 2, 0), chol).permute(2, 0, 1)
        quad = (r * r * self.noise).sum((2, 3)) - (u * sol).sum(-1)  # r^T R^-1 r - u^T P^-1 u
        # |H S H^T + R| = |R| |S| |P_c| (matrix determinant lemma)
        logdet = 2 * (
            chol.diagonal(dim1=-2, dim2=-1).log().sum(-1) + self.cov_chol.diagonal().log().sum()
        ) + t * self.noise.log().sum()  # fmt: skip
        log_ev = -0.5 * (quad + logdet + t * d * math.log(2 * math.pi))  # [B, C]
        return log_ev - math.log(C), self.mean + sol, chol  # a uniform prior over candidates

    def condition(self, prefix: Any) -> PrefixPosterior:
        """Condition on the first ``t`` frames of ``B`` movements, ``prefix [B, t, D]``
        (``t = 0``: the prior), mixing the candidate durations by their evidence.

        Raises:
            RuntimeError: before :meth:`fit`.
            ValueError: a prefix that is not ``[B, t, D]`` or not finite.
        """
        y = self._checked(prefix)
        b, n_w, C = y.shape[0], self.dim * self.num_basis, len(self.durations)
        if y.shape[1] == 0:
            e_mean, e_cov = self.mean[n_w:], self.cov[n_w:, n_w:]
            weights = y.new_full((b, C), 1.0 / C)
            return PrefixPosterior(
                y.new_zeros(b), e_mean.expand(b, -1), e_cov.expand(b, -1, -1), weights
            )
        log_ev, z_mean, chol = self._per_duration(y)
        total = torch.logsumexp(log_ev, 1)
        weights = (log_ev - total[:, None]).exp()
        # e | Y, T_c: the extras' part of the posterior mean, covariance (P_c^-1)_ee
        means = z_mean[..., n_w:]  # [B, C, E]
        eye = torch.eye(n_w + self.num_extras, dtype=y.dtype)[:, n_w:]
        covs = torch.cholesky_solve(eye.expand(C, -1, -1), chol)[:, n_w:]  # [C, E, E]
        mean = (weights[..., None] * means).sum(1)
        spread = means - mean[:, None]
        cov = torch.einsum("bc,cef->bef", weights, covs) + torch.einsum(
            "bc,bce,bcf->bef", weights, spread, spread
        )
        return PrefixPosterior(total, mean, cov, weights)

    def sample_next(
        self, prefix: Any, num: int, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Draws of the frame after the prefix ``[B, t >= 1, D]``: ``[B, num, D]`` from the
        predictive mixture over the durations, ``y_t | Y, T_c ~ N(H_c(t) E[w], H_c(t)
        P_c^-1 H_c(t)^T + R)``.

        Raises:
            RuntimeError: before :meth:`fit`.
            ValueError: an empty or malformed prefix, ``num < 1``.
        """
        y = self._checked(prefix)
        num = positive_int(num, "num")
        b, t, d = y.shape
        if t == 0:
            raise ValueError("prefix must hold at least one frame to predict the next from")
        log_ev, z_mean, chol = self._per_duration(y)
        phi = self.basis(t + 1, self.durations)[:, -1]  # [C, B]: frame t of each candidate
        H = torch.kron(torch.eye(d, dtype=y.dtype), phi[:, None, :])  # [C, D, D B]
        H = torch.nn.functional.pad(H, (0, self.num_extras))  # [C, D, M]
        mean = torch.einsum("cdm,bcm->bcd", H, z_mean)  # [B, C, D]
        cov = H @ torch.cholesky_solve(H.mT, chol) + torch.diag(self.noise)  # [C, D, D]
        pick = torch.multinomial(log_ev.softmax(1), num, replacement=True, generator=generator)
        eps = torch.randn(b, num, d, dtype=y.dtype, generator=generator)
        scale = torch.linalg.cholesky(cov)[pick]  # [B, num, D, D]
        return mean.gather(1, pick[..., None].expand(-1, -1, d)) + (scale @ eps[..., None])[..., 0]

    def log_likelihood(self, prefix: Any) -> torch.Tensor:
        """``log p(prefix) [B]`` of ``prefix [B, t, D]``, mixed over the durations."""
        return self.condition(prefix).log_evidence


#: the options :class:`ProMPRegressor` chooses among by cross-validation
PROMP_GRID: dict[str, tuple] = {
    "num_basis": (3, 4, 6, 8),
    "speeds": ((1.0,), (0.8, 0.9, 1.0, 1.12, 1.25)),
    "reg": (1e-6, 1e-2),
}

#: the options :class:`ProMPClassifier` chooses among (one ProMP per class: a smaller grid)
PROMP_CLASS_GRID: dict[str, tuple] = {
    "num_basis": (4, 8),
    "speeds": ((1.0,), (0.67, 0.8, 1.0, 1.25, 1.5)),
}

_OPTIONS = {"num_basis", "speeds", "reg", "durations", "bandwidth"}


def _prefix_posteriors(model: ProMP, z: torch.Tensor) -> list[PrefixPosterior]:
    """The posterior after each frame of ``z [M, T, D]``: ``T`` of them."""
    return [model.condition(z[:, : t + 1]) for t in range(z.shape[1])]


class _Selected:
    """Options chosen from a grid by ``folds``-fold cross-validation over whole training
    movements (the folds of a seeded permutation): the lowest mean held-out score."""

    def __init__(self, grid: dict[str, Sequence] | None, folds: int, seed: int) -> None:
        grid = dict(self.GRID if grid is None else grid)
        if set(grid) - _OPTIONS or not all(len(v) for v in grid.values()):
            raise ValueError(
                f"grid must map ProMP options ({sorted(_OPTIONS)}) to non-empty candidate "
                f"lists, got {grid!r}"
            )
        self.grid, self.folds, self.seed = grid, positive_int(folds, "folds"), int(seed)

    GRID: dict[str, tuple] = {}

    def _select(self, num: int, score, labels: torch.Tensor | None = None) -> dict[str, Any]:
        """The options minimising ``score(options, train, held) -> [items]`` over the folds
        (``self.scores``: each configuration's mean); with ``labels [num]``, folds stratified
        by class (every ``folds``-th movement of each class held out together)."""
        from ..crossval import contiguous_folds, interleaved_folds

        configs: list[dict[str, Any]] = [{}]
        for name, values in self.grid.items():
            configs = [c | {name: v} for c in configs for v in values]
        if len(configs) == 1:
            return configs[0]
        gen = torch.Generator().manual_seed(self.seed)
        perm = torch.randperm(num, generator=gen)
        folds = min(self.folds, num)
        if labels is None:
            splits = contiguous_folds(num, folds)
        else:
            perm = perm[torch.argsort(labels[perm], stable=True)]
            splits = interleaved_folds(num, folds)
        order = perm.tolist()
        self.scores = []
        for options in configs:
            parts = [
                score(options, [order[i] for i in train], [order[i] for i in held])
                for train, held in splits
            ]
            self.scores.append(float(torch.cat(parts).mean()))
        return configs[min(range(len(configs)), key=self.scores.__getitem__)]


class ProMPRegressor(_Selected):
    """A continuous target from a movement's prefix: a :class:`ProMP` over the channels joint
    with the target, conditioned on frames ``0..t`` at every step ``t``.

    The options (``num_basis``, the speeds of the phase estimation, the weight ridge) are
    chosen from ``grid`` (:data:`PROMP_GRID`) by ``folds``-fold cross-validation: the lowest
    MAE over all steps of the held-out movements (``scores``: each configuration's).

    Args:
        grid: option name -> candidates; options not in it take :class:`ProMP`'s defaults.
        folds: cross-validation folds (at most the number of movements).
        seed: seed of the folds' permutation.
    """

    GRID = PROMP_GRID

    def __init__(
        self, grid: dict[str, Sequence] | None = None, *, folds: int = 5, seed: int = 0
    ) -> None:
        super().__init__(grid, folds, seed)

    def fit(self, sequences: Any, targets: Any) -> ProMPRegressor:
        """Fit on movements ``[T_i, D]`` with one target each ``[n]``.

        Raises:
            ValueError: not one finite target per movement.
        """
        seqs = as_sequences(sequences)
        y = as_tensor(targets, "targets", dtype=torch.float64, ndim=1)
        if y.shape[0] != len(seqs):
            raise ValueError(f"need one target per sequence: {y.shape[0]} for {len(seqs)}")

        def mae(options: dict, train: list[int], held: list[int]) -> torch.Tensor:
            model = ProMP(**options).fit([seqs[i] for i in train], y[train])
            out = []
            for length in sorted({seqs[i].shape[0] for i in held}):  # equal lengths at once
                same = [i for i in held if seqs[i].shape[0] == length]
                z = torch.stack([seqs[i] for i in same]).double()
                mean = torch.stack([p.mean[:, 0] for p in _prefix_posteriors(model, z)], 1)
                out.append((mean - y[same, None]).abs().flatten())
            return torch.cat(out)

        self.options = self._select(len(seqs), mae)
        self.model = ProMP(**self.options).fit(seqs, y)
        return self

    def predict(self, z: Any) -> tuple[torch.Tensor, torch.Tensor]:
        """Predictive mean and std of the target at every step: ``[M, T, D]`` -> ``[M, T]``.

        Raises:
            RuntimeError: before :meth:`fit`.
        """
        check_fitted(self, "model", "fit(sequences, targets)")
        z = as_tensor(z, "z", dtype=torch.float64, ndim=3)
        posts = _prefix_posteriors(self.model, z)
        mean = torch.stack([p.mean[:, 0] for p in posts], 1)
        return mean, torch.stack([p.cov[:, 0, 0] for p in posts], 1).sqrt()


class ProMPClassifier(_Selected):
    """A class from a movement's prefix: one :class:`ProMP` per class, the class posterior
    ``p(c | y_0..t) ~ p(y_0..t | c) p(c)`` from each class's prefix likelihood (its phase
    estimated) and the training frequencies, at every step ``t``.

    The options are chosen from ``grid`` (:data:`PROMP_CLASS_GRID`) by ``folds``-fold
    cross-validation: the lowest error rate over all steps of the held-out movements (with
    ``online=False``, of their decisions at the end: :meth:`window_log_proba`).

    Args:
        grid: option name -> candidates; options not in it take :class:`ProMP`'s defaults.
        folds: cross-validation folds (at most the number of movements).
        seed: seed of the folds' permutation.
        online: whether the decisions that count are those after every frame
            (:meth:`predict_log_proba`) or one per whole movement or window.
    """

    GRID = PROMP_CLASS_GRID

    def __init__(
        self,
        grid: dict[str, Sequence] | None = None,
        *,
        folds: int = 3,
        seed: int = 0,
        online: bool = True,
    ) -> None:
        super().__init__(grid, folds, seed)
        if not isinstance(online, bool):
            raise TypeError(f"online must be a bool, got {online!r}")
        self.online = online

    @staticmethod
    def _fit_classes(options, seqs, y, classes: int) -> tuple[list[ProMP | None], torch.Tensor]:
        """One ProMP per class and the log class frequencies; a class with fewer than 2
        movements here (a cross-validation fold of a small class) gets neither."""
        counts = torch.bincount(y, minlength=classes)
        models = [
            ProMP(**options).fit([s for s, c in zip(seqs, y, strict=True) if c == k])
            if counts[k] >= 2 else None
            for k in range(classes)
        ]  # fmt: skip
        usable = (counts * torch.tensor([m is not None for m in models])).double()
        if usable.sum() == 0:  # no class fits in this fold: every class equally likely
            return models, usable
        return models, (usable / usable.sum()).log()

    @staticmethod
    def _log_proba(models, log_prior, z: torch.Tensor, every_step: bool = True) -> torch.Tensor:
        """``[M, T, C]`` log posteriors after every frame of ``z [M, T, D]`` (``[M, 1, C]`` of
        the whole ``z`` unless ``every_step``)."""
        steps = [
            z.new_zeros(len(z), z.shape[1] if every_step else 1) if m is None  # its prior is 0
            else torch.stack([p.log_evidence for p in _prefix_posteriors(m, z)], 1) if every_step
            else m.log_likelihood(z)[:, None]
            for m in models
        ]  # fmt: skip
        joint = torch.stack(steps, -1) + log_prior  # [M, T, C]
        return joint - torch.logsumexp(joint, -1, keepdim=True)

    def fit(self, sequences: Any, labels: Any) -> ProMPClassifier:
        """Fit on movements ``[T_i, D]`` with one class code each ``[n]`` (codes ``0..C-1``,
        each class with at least 2 movements).

        Raises:
            ValueError: labels that are not one non-negative integer code per movement, or a
                class with fewer than 2 movements.
        """
        seqs = as_sequences(sequences)
        y = torch.as_tensor(labels)
        if y.dim() != 1 or y.shape[0] != len(seqs) or y.is_floating_point() or (y < 0).any():
            raise ValueError(
                f"labels must be [n] non-negative integer codes, one per movement (n = "
                f"{len(seqs)}), got {tuple(y.shape)} {y.dtype}"
            )
        y = y.long()
        C = int(y.max()) + 1
        small = [k for k, n in enumerate(torch.bincount(y).tolist()) if n < 2]
        if small:
            raise ValueError(f"labels: classes {small} have fewer than 2 movements")

        def errors(options: dict, train: list[int], held: list[int]) -> torch.Tensor:
            models, prior = self._fit_classes(options, [seqs[i] for i in train], y[train], C)
            out = []
            for length in sorted({seqs[i].shape[0] for i in held}):  # equal lengths at once
                same = [i for i in held if seqs[i].shape[0] == length]
                z = torch.stack([seqs[i] for i in same]).double()
                pred = self._log_proba(models, prior, z, every_step=self.online).argmax(-1)
                out.append(pred.ne(y[same, None]).double().flatten())
            return torch.cat(out)

        self.options = self._select(len(seqs), errors, labels=y)
        self.models, self.log_prior = self._fit_classes(self.options, seqs, y, C)
        return self

    def predict_log_proba(self, z: Any) -> torch.Tensor:
        """Log class posteriors at every step: ``[M, T, D]`` -> ``[M, T, C]``.

        Raises:
            RuntimeError: before :meth:`fit`.
        """
        check_fitted(self, "models", "fit(sequences, labels)")
        z = as_tensor(z, "z", dtype=torch.float64, ndim=3)
        return self._log_proba(self.models, self.log_prior, z)

    def window_log_proba(self, z: Any) -> torch.Tensor:
        """Log class posteriors of whole movements or windows: ``[M, T, D]`` -> ``[M, C]``.

        Raises:
            RuntimeError: before :meth:`fit`.
        """
        check_fitted(self, "models", "fit(sequences, labels)")
        z = as_tensor(z, "z", dtype=torch.float64, ndim=3)
        return self._log_proba(self.models, self.log_prior, z, every_step=False)[:, 0]

    def predict(self, z: Any) -> torch.Tensor:
        """Most probable class at every step: ``[M, T]`` (long)."""
        return self.predict_log_proba(z).argmax(-1)
