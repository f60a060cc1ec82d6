r"""Variational Bayes inference of the exogenous variable and the latent states of a new window:
Algorithm 2.2 of the thesis (Sec. 2.3), and its result.

For every candidate value of g, the mean-field q of Eq. 11 maximises the negative free energy
``F(q, g)`` of Eq. 13 (Eq. 15-17), which approximates ``log p(z_{1:T} | g)`` (Eq. 10); the
posterior over g follows from these bounds and the prior. All windows and candidates are solved
in one batched optimisation:

1. initial states (:func:`~hgpdm_torch.inference.variational.initial.initial_guess`);
2. the mean-field Laplace start
   (:func:`~hgpdm_torch.inference.variational.laplace.laplace`): Levenberg-Marquardt to the MAP
   states, then ``Sigma_t`` the inverse diagonal blocks of the Fisher precision;
3. the exact F, maximised either in closed form by L-BFGS
   (:func:`~hgpdm_torch.inference.variational.polish.polish`, ``method="closed_form"``, the
   default) or through Pyro, ``pyro.infer.SVI`` on the
   :class:`~hgpdm_torch.inference.variational.guide.MeanFieldGuide` with the closed-form F (or
   ``Trace_ELBO``) as its loss (:func:`~hgpdm_torch.inference.variational.svi.fit_svi`,
   ``method="svi"``).

The closed form is the default because it is exact and deterministic: a batched quasi-Newton
method with per-problem line searches converges in tens of iterations to the optimum that SVI's
first-order steps (Adam) approach only over hundreds, and its results do not depend on a learning
rate schedule. For a discrete g (and a GPDM) SVI reaches the same optimum with its default
settings (tests/inference/test_svi.py). For a continuous g the Laplace start leaves q(g) at its
prior, far from the optimum: with the defaults (300 steps) SVI stops tens of nats short, and it
needs about 2,000 steps or ``lr=0.05``. SVI is there to run VB with Pyro's machinery (other
guides, Monte-Carlo ELBOs).

Shapes: ``T`` window length, ``K`` candidate values of g, ``Dx`` latent dim, ``Dz`` observation
dim, ``Dg`` dim of a continuous g; ``...`` leading batch dims (e.g. windows).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from ...validation import check_choice
from . import prediction
from .engine import WindowEngine
from .guide import MeanFieldGuide
from .laplace import check_prune, laplace
from .polish import polish
from .svi import SVIOptions, fit_svi, pyro_model
from .window import window_mask

__all__ = ["METHODS", "VBResult", "VariationalInference"]

METHODS = ("closed_form", "svi")


@dataclass
class VBResult:
    """Output of :meth:`VariationalInference.infer` (Algorithm 2.2).

    Attributes:
        values: ``[K]`` candidate values of g (codes of a discrete g; empty for a GPDM or a
            continuous g, where ``K = 1``).
        log_evidence: ``[..., K]`` maximised ``F(q, g)``, the approximate ``log p(z_{1:T} | g)``.
        posterior: ``[..., K]`` ``p(g | z_{1:T})`` from ``log_evidence`` and the prior over g.
        g_ml: ``[...]`` index into ``values`` of the largest ``log_evidence`` (the ML value).
        mean: ``[..., K, T, Dx]`` means of q(x) per candidate g.
        cov: ``[..., K, T, Dx, Dx]`` covariances of q(x).
        g_mean: ``[..., Dg]`` mean of q(g) (continuous g), else ``None``.
        g_cov: ``[..., Dg, Dg]`` covariance of q(g), else ``None``.
        guide: the fitted :class:`MeanFieldGuide`.
        history: ``-sum F`` over all windows and candidates after each optimiser iteration
            (with ``method="svi"``: the SVI loss after each step).
        map_states: ``[..., K, T, Dx]`` the Laplace start's means, the Levenberg-Marquardt
            maximisers of the log joint per candidate: the MAP baseline's states
            (:class:`~hgpdm_torch.inference.map.MAPInference` with ``steps=newton_steps``, the
            same start and no pruning), at no extra cost; ``None`` with ``newton_steps=0``.
    """

    values: torch.Tensor
    log_evidence: torch.Tensor
    posterior: torch.Tensor
    g_ml: torch.Tensor
    mean: torch.Tensor
    cov: torch.Tensor
    g_mean: torch.Tensor | None
    g_cov: torch.Tensor | None
    guide: MeanFieldGuide
    history: list[float]
    map_states: torch.Tensor | None = None

    def ml_state(self) -> tuple[torch.Tensor, torch.Tensor]:
        """q(x) of the ML value of g: ``mean [..., T, Dx]`` and ``cov [..., T, Dx, Dx]``."""
        return self.select(self.g_ml)

    def select(self, index: torch.Tensor | int) -> tuple[torch.Tensor, torch.Tensor]:
        """q(x) for candidate ``index`` (``[...]`` or an int): mean ``[..., T, Dx]``, cov."""
        index = torch.as_tensor(index, device=self.mean.device).expand(self.mean.shape[:-3])
        i = index[..., None, None, None]
        T, D = self.mean.shape[-2:]
        mean = self.mean.gather(-3, i.expand(*index.shape, 1, T, D))[..., 0, :, :]
        cov = self.cov.gather(-4, i[..., None].expand(*index.shape, 1, T, D, D))
        return mean, cov[..., 0, :, :, :]


class VariationalInference(WindowEngine):
    """Variational Bayes inference in a fitted GPDM / H-GPDM (Sec. 2.3, Algorithm 2.2).

    Args:
        model: a fitted :class:`~hgpdm_torch.models.GPDM` (no g), or an
            :class:`~hgpdm_torch.models.HGPDM` / ``IDDM`` with a discrete or continuous g.

    The keywords ``x1_prior``, ``g_prior`` and ``measurement_points`` (the window model's priors
    and measurement GP) are those of
    :class:`~hgpdm_torch.inference.variational.engine.WindowEngine`.

    Attributes:
        window: the :class:`~hgpdm_torch.inference.variational.window.WindowModel` (GPs, priors,
            objectives) this engine shares with the MAP baseline.
        model, kind, values, measurement, transition, latent_dim, obs_dim: the window model's.

    Example:
        >>> vb = VariationalInference(model)                   # doctest: +SKIP
        >>> res = vb.infer(window)                             # doctest: +SKIP
        >>> res.posterior, res.g_ml                            # doctest: +SKIP
    """

    # ------------------------------------------------------------------ the objective
    def free_energy(
        self,
        z: object,
        loc: torch.Tensor,
        scale_tril: torch.Tensor,
        *,
        values: object = None,
        g_loc: torch.Tensor | None = None,
        g_scale_tril: torch.Tensor | None = None,
    ) -> torch.Tensor:
        r"""Negative free energy ``F(q, g)`` of Eq. 13 with Eq. 15-17, in closed form.

        Args:
            z: ``[..., T, Dz]`` window; NaN rows are missing (their measurement term is dropped).
            loc: ``[..., K, T, Dx]`` means of q(x), one set per candidate g.
            scale_tril: ``[..., K, T, Dx, Dx]`` lower Cholesky factors of the covariances.
            values: ``[K]`` (or ``[..., K]``) candidate codes of a discrete g (default all K).
            g_loc: ``[..., Dg]`` mean of q(g) of a continuous g.
            g_scale_tril: ``[..., Dg, Dg]`` Cholesky factor of the covariance of q(g).

        Returns:
            ``[..., K]`` F for each candidate (``K = 1`` without a discrete g).
        """
        z, observed = window_mask(z, self.obs_dim, self.window.x1_mean)
        values = self.window.candidates(values)
        return self.window.free_energy(z, observed, loc, scale_tril, values, g_loc, g_scale_tril)

    def guide_free_energy(
        self, z: object, guide: MeanFieldGuide, *, values: object = None
    ) -> torch.Tensor:
        """:meth:`free_energy` of a :class:`MeanFieldGuide` ``[..., K]``."""
        loc, tril, g_loc, g_tril = guide.q()
        return self.free_energy(z, loc, tril, values=values, g_loc=g_loc, g_scale_tril=g_tril)

    def pyro_model(self, z: object, guide: MeanFieldGuide, *, values: object = None) -> None:
        """Pyro model whose ELBO against ``guide`` is :meth:`free_energy`
        (:func:`~hgpdm_torch.inference.variational.svi.pyro_model`; an independent Monte-Carlo
        check of the closed form with ``pyro.infer.Trace_ELBO``)."""
        z, observed = window_mask(z, self.obs_dim, self.window.x1_mean)
        pyro_model(self.window, z, observed, self.window.candidates(values), guide)

    # ------------------------------------------------------------------ Algorithm 2.2
    def infer(
        self,
        z: object,
        *,
        values: object = None,
        steps: int = 0,
        newton_steps: int = 30,
        prune: float | None = 50.0,
        init: str = "nearest",
        method: str = "closed_form",
        svi: SVIOptions | None = None,
        progress: bool = False,
    ) -> VBResult:
        """Algorithm 2.2: maximise F(q, g) for every candidate g in one batched optimisation.

        Every window and candidate g is its own problem, all solved in the same tensor calls:

        1. initial states (:meth:`initial_guess`);
        2. :func:`~hgpdm_torch.inference.variational.laplace.laplace`: Levenberg-Marquardt to
           the MAP states, then the mean-field Laplace covariances (the optimum of F to second
           order; cheap: GP predictions at points only);
        3. ``steps`` iterations on the exact F: L-BFGS on the closed form (``method=
           "closed_form"``, the default: exact, deterministic and fast) or ``pyro.infer.SVI`` on
           the :class:`MeanFieldGuide` (``method="svi"``; its loss, closed-form F or Pyro's
           ``Trace_ELBO``, and learning rates in ``svi``), which reaches the same optimum with
           more, first-order steps (for a continuous g many more: see the module docstring).

        Without step 2 (``newton_steps=0``) L-BFGS alone stalls hundreds of nats below the
        optimum from a GP-RTSS start: F is stiff (process noise ``alpha_4 = 1e-4``), so a
        first-order method crawls, and the comparison across g is then between unconverged
        bounds.

        Args:
            z: ``[..., T, Dz]`` window (``T >= 2``); NaN rows are missing observations (to be
                forecast or recovered), at least one row must be observed.
            values: candidate codes of a discrete g, ``[K]`` or ``[..., K]`` (default all); e.g.
                the true code ``[..., 1]`` for the oracle H-GPDM.
            steps: maximum L-BFGS iterations on F after the Laplace start (``method="svi"``: SVI
                steps, at least one).
            newton_steps: maximum Levenberg-Marquardt iterations of the Laplace start (0: start
                step 3 from ``init`` directly).
            prune: the Laplace start stops refining a candidate g whose log joint trails the
                window's best candidate by more than ``prune`` nats: its posterior weight is
                below ``exp(-prune)`` either way, and its ``log_evidence`` is then a looser (still
                valid) lower bound. ``None`` refines every candidate to convergence.
            init: initial states (see :meth:`initial_guess`).
            method: ``"closed_form"`` or ``"svi"`` (step 3).
            svi: :class:`~hgpdm_torch.inference.variational.svi.SVIOptions` of ``method="svi"``
                (default: closed-form loss, Adam from 5e-3 decaying to 1e-5).
            progress: show a progress bar over the iterations of step 3.

        Returns:
            :class:`VBResult`.
        """
        w = self.window
        z, observed = window_mask(z, self.obs_dim, self.window.x1_mean)
        for name, v in (("steps", steps), ("newton_steps", newton_steps)):
            if not isinstance(v, int) or v < 0:
                raise ValueError(f"{name} must be a non-negative int, got {v!r}")
        check_prune(prune)
        check_choice(method, "method", METHODS)
        if method == "svi" and steps == 0:
            raise ValueError("method='svi' needs steps > 0 (the number of SVI steps)")
        if svi is not None and method != "svi":
            raise ValueError("svi options apply to method='svi' only")
        values = w.candidates(values)
        loc, cov, g_loc, g_cov = self.initial_guess(z, values, init)
        map_states = None
        if newton_steps:
            loc, cov = laplace(
                w, z, observed, loc, values, g_loc, max_iter=newton_steps, prune=prune
            )
            map_states = loc.detach()
        history: list[float] = []
        if steps and method == "closed_form":
            (loc, cov, g_loc, g_cov), history = polish(
                w, z, observed, values, (loc, cov, g_loc, g_cov), steps, progress
            )
        elif steps:
            fitted = MeanFieldGuide(loc, cov, g_loc, g_cov)
            history = fit_svi(w, z, observed, values, fitted, steps, svi, progress)
            with torch.no_grad():
                loc, cov = fitted.loc.detach(), fitted.cov.detach()
                if fitted.has_g:
                    g_loc, g_cov = fitted.g_loc.detach(), fitted.g_cov.detach()
        with torch.no_grad():
            guide = MeanFieldGuide(loc, cov, g_loc, g_cov)
            q_loc, tril, g_l, g_tril = guide.q()
            F = w.free_energy(z, observed, q_loc, tril, values, g_l, g_tril)
            history = history or [float(-F.sum())]
            if not bool(torch.isfinite(F).all()):
                raise FloatingPointError("the free energy is not finite after optimisation")
            return VBResult(
                values=values,
                log_evidence=F,
                posterior=torch.softmax(F + w.log_prior(values), dim=-1),
                g_ml=F.argmax(-1),
                mean=guide.loc.detach(),
                cov=guide.cov.detach(),
                g_mean=guide.g_loc.detach() if guide.has_g else None,
                g_cov=guide.g_cov.detach() if guide.has_g else None,
                guide=guide,
                history=history,
                map_states=map_states,
            )

    # ------------------------------------------------------------------ prediction (Sec. 2.3.2)
    def observation_marginals(
        self, mean: torch.Tensor, cov: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Moment-matched ``q(z_t)`` per time step: see
        :func:`~hgpdm_torch.inference.variational.prediction.observation_marginals`."""
        return prediction.observation_marginals(self.window, mean, cov)

    def observation_joint(
        self, mean: torch.Tensor, cov: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Gaussian ``q(z_{1:T})`` with cross-time covariances (App. 2.B): see
        :func:`~hgpdm_torch.inference.variational.prediction.observation_joint`."""
        return prediction.observation_joint(self.window, mean, cov)

    def predict_observations(
        self, z: object, result: VBResult, *, joint: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Predict every row of a window from q(x) of the ML value of g (Sec. 2.3.2).

        Missing (NaN) rows are forecast or recovered: with ``joint=True`` from
        ``q(z_missing | z_observed)`` (the joint of :meth:`observation_joint` conditioned on the
        observed rows); with ``joint=False`` from the per-step marginals ``q(z_t)`` (FIC).

        Args:
            z: ``[..., T, Dz]`` the window passed to :meth:`infer`.
            result: its :class:`VBResult`.

        Returns:
            ``mean [..., T, Dz]`` (observed rows unchanged when ``joint``) and ``var [..., T, Dz]``.
        """
        z, observed = window_mask(z, self.obs_dim, self.window.x1_mean)
        mean, cov = result.ml_state()
        return prediction.predict_observations(self.window, z, observed, mean, cov, joint=joint)

    def reconstruct(self, result: VBResult) -> tuple[torch.Tensor, torch.Tensor]:
        """Unconditioned predictions of every row from q(x) of the ML g: the moment-matched
        ``q(z_t)`` means ``[..., T, Dz]`` and variances ``[..., T, Dz]`` (noise included)."""
        mean, cov = result.ml_state()
        with torch.no_grad():
            m, S = self.observation_marginals(mean, cov)
        return m, S.diagonal(dim1=-2, dim2=-1)

    def forecast(
        self, z: object, *, residual: str | None = None, **infer_kwargs: Any
    ) -> tuple[torch.Tensor, torch.Tensor, VBResult]:
        """Forecast ``z_{T+1}`` from a window ``z_{1:T}`` (Sec. 2.3.2, Tables 2.1-2.4 protocol).

        Runs :meth:`infer` on ``z_{1:T}`` with a missing row appended, picks the ML value of g
        and conditions the joint ``q(z_{1:T+1})`` on the observed rows
        (:func:`~hgpdm_torch.inference.variational.prediction.forecast`).

        Args:
            z: ``[..., T, Dz]`` windows (NaN marks missing values).
            residual: ``None`` (the thesis's forecast) or ``"ar1"``: the window's deviation from
                the model's reconstruction continues as an AR(1) process whose coefficient is
                estimated from the window (:func:`~hgpdm_torch.inference.residual.
                ar1_residual_forecast`); for new recordings that sit off the training manifold.
            **infer_kwargs: passed to :meth:`infer`.

        Returns:
            ``mean [..., Dz]``, ``var [..., Dz]`` of the next observation, and the result.
        """
        return prediction.forecast(self, z, residual=residual, **infer_kwargs)
