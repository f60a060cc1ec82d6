r"""Variational Bayes inference of the exogenous variable and the latent states of a new window
(thesis Sec. 2.3, Algorithm 2.2, App. 2.A-2.B).

Given a fitted :class:`~hgpdm_torch.models.GPDM` / :class:`~hgpdm_torch.models.HGPDM` (its MAP
training latents define a measurement GP ``h`` and a transition GP ``f``) and a window of
observations ``z_{1:T}``, the mean-field family (Eq. 11)

    q(x_{1:T}) = prod_t N(x_t | mu_t, Sigma_t)        [and q(g) = N(mu_g, Sigma_g), Sec. 2.3.3]

is fitted by maximising the negative free energy of Eq. 13 under the FIC factorisation (Eq. 8-9):

    F(q, g) = sum_t E_q[log p(z_t | x_t)] + sum_t E_q[log p(x_{t+1} | x_t, g)]
              - H(q(x_1), p(x_1)) + H(q)     [+ E_q[log p(g)] + H(q(g)) for a continuous g]

with the GP predictive variances evaluated at the variational means (Eq. 15-17). One module per
concept:

- :mod:`~.guide`: the variational family as a Pyro guide (Eq. 11);
- :mod:`~.gaussian_input`: GP means and variances at Gaussian inputs (App. 2.A);
- :mod:`~.window`: the model seen by a window, with the log joint (Eq. 8-9) and F (Eq. 13,
  15-17), shared by VB and the MAP baseline (:mod:`hgpdm_torch.inference.map`);
- :mod:`~.initial`: initial states (Algorithm 2.2, step 1);
- :mod:`~.engine`: :class:`~.engine.WindowEngine`, the window model and initial states of VB and
  the MAP baseline;
- :mod:`~.laplace`: Levenberg-Marquardt to the MAP states and the mean-field Laplace start;
- :mod:`~.lbfgs` and :mod:`~.polish`: batched L-BFGS on the exact F in whitened coordinates;
- :mod:`~.svi`: the Pyro model and ``pyro.infer.SVI`` on the guide;
- :mod:`~.prediction`: forecasting and gap recovery (Sec. 2.3.2, App. 2.B);
- :mod:`~.algorithm`: :class:`VariationalInference` (Algorithm 2.2) and :class:`VBResult`.

Shapes: ``T`` window length, ``K`` candidate values of g, ``Dx`` latent dim, ``Dz`` observation
dim, ``Dg`` dim of a continuous g; ``...`` leading batch dims (e.g. windows).
"""

from ...gaussian import condition_gaussian
from .algorithm import VariationalInference, VBResult
from .guide import MeanFieldGuide
from .lbfgs import batched_lbfgs
from .svi import SVIOptions
from .window import WindowModel, window_mask

__all__ = [
    "MeanFieldGuide",
    "SVIOptions",
    "VBResult",
    "VariationalInference",
    "WindowModel",
    "batched_lbfgs",
    "condition_gaussian",
    "window_mask",
]
