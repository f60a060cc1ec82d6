# ---
# jupyter:
#   jupytext:
#     notebook_metadata_filter: -jupytext.text_representation.jupytext_version
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 01 · H-GPDM basics
#
# A Hierarchical Gaussian Process Dynamics Model (H-GPDM, thesis Ch. 2) explains movements by latent
# trajectories whose GP dynamics depend on an exogenous variable *g* (a style, an intention, a
# target). In this tutorial we
#
# 1. generate synthetic movements in three styles,
# 2. define an H-GPDM and fit it by MAP (Eq. 6) with the built-in `fit` and with our own torch loop,
# 3. discover the styles without labels (Algorithm 2.1),
# 4. plot latent trajectories and mean rollouts of each style's dynamics,
# 5. build the model with kernels of our own and infer the style online.

# %%
import os

import matplotlib.pyplot as plt
import torch

import hgpdm_torch as hg

SMOKE = os.environ.get('HGPDM_SMOKE') == '1'  # CI runs this notebook with smaller sizes
torch.manual_seed(0)
data = hg.datasets.styled_movements(num_styles=3, per_style=3 if SMOKE else 5,
                                    length=25 if SMOKE else 50, obs_dim=12, seed=0)
print(len(data.sequences), 'sequences of shape', tuple(data.sequences[0].shape),
      'styles', data.labels.tolist())

# %% [markdown]
# ## Define and fit
#
# `HGPDM(sequences, intentions, latent_dim)` takes a list of `[T, Dz]` sequences (lengths may
# differ) and one *g* per sequence. Latent states are initialised by PCA; the transition
# hyperparameters are fixed to the thesis's alpha-bar unless `learn_alpha=True`.
#
#
# `fit(steps)` is a step budget. The MAP objective (Eq. 6) of these 750 latent coordinates keeps
# falling slowly long after the trajectories have taken their shape: after 4,000 L-BFGS steps
# (4 minutes) it still falls by about 1e-4 (relative) every 5 steps, far from the fit's
# convergence criterion (a relative change below 1e-9). We stop at 80 steps, and the printed
# `FitResult` says that the fit did not converge and how fast the loss still fell; `warn=False`
# keeps the same message from also appearing as a warning.

# %%
model = hg.HGPDM(data.sequences, data.labels, latent_dim=3, measurement='rbf')
fit = model.fit(steps=20 if SMOKE else 80, warn=False)
print(fit)  # FitResult: converged or not, and why
plt.plot(fit.history)
plt.xlabel('L-BFGS step')
plt.ylabel('negative log posterior (Eq. 6)')
plt.show()

# %% [markdown]
# The model is an ordinary torch module and its objective stands beside it, as gpytorch's
# marginal log likelihood does: `model.objective()` is the negative log posterior of Eq. 6, a
# module over the model's parameters with its named terms. Any optimizer and loop work:

# %%
own = hg.GPDM(data.sequences, latent_dim=3)
objective = own.objective()
opt = torch.optim.Adam(own.parameters(), lr=0.02)
for _ in range(30 if SMOKE else 200):
    opt.zero_grad()
    loss = objective()
    loss.backward()
    opt.step()
print(f'GPDM loss after Adam: {loss.item():.1f};',
      {name: round(term.item(), 1) for name, term in objective.terms().items()})

# %% [markdown]
# ## Discover styles without labels (Algorithm 2.1)
#
# Alternate assigning each sequence the style that maximises the joint posterior and re-fitting the
# model.

# %%
from hgpdm_torch.experiments.style_discovery import style_purity

found = hg.HGPDM.discover(data.sequences, num_styles=3, iterations=3 if SMOKE else 8,
                          steps=15 if SMOKE else 40, seed=0)
print('discovered', found.intention_codes().tolist())
print('true      ', data.labels.tolist())
print('purity', style_purity(data.labels, found.intention_codes()))

# %% [markdown]
# ## Latent trajectories and mean rollouts
#
# Left: the learned latent trajectories, coloured by style. Right: the mean of each style's
# transition GP rolled out from the same start state: one set of training data, three dynamics.

# %%
fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
for lat, k in zip(model.latent_sequences(), data.labels, strict=True):
    a.plot(lat[:, 0], lat[:, 1], color=f'C{int(k)}', lw=1)
a.set(title='latent trajectories', xlabel='$x_1$', ylabel='$x_2$')
x0 = model.latent_sequences()[0][0]
for k in range(3):
    path = model.rollout(x0, steps=40, g=k)
    b.plot(path[:, 0], path[:, 1], color=f'C{k}', label=f'style {k}')
b.legend()
b.set(title='mean rollouts from one start', xlabel='$x_1$')
plt.show()

# %% [markdown]
# Rolled-out latents map back to observations through the measurement GP; here we compare one
# observed dimension with its reconstruction.

# %%
z_mean, z_var = model.measurement_posterior().predict(model.latent_sequences()[0])
z = data.sequences[0]
t = torch.arange(len(z))
plt.plot(t, z[:, 0], 'k.', label='observed')
plt.plot(t, z_mean[:, 0], label='reconstruction')
band = 2 * z_var[:, 0].sqrt()
plt.fill_between(t, z_mean[:, 0] - band, z_mean[:, 0] + band, alpha=0.3)
plt.legend()
plt.xlabel('frame')
plt.show()

# %% [markdown]
# Save and load round-trip exactly:

# %%
import pathlib
import tempfile

path = pathlib.Path(tempfile.mkdtemp()) / 'hgpdm.pt'
model.save(path)
again = hg.load_model(path)
assert again.loss().item() == model.loss().item()
print('reloaded', type(again).__name__)

# %% [markdown]
# ## Kernels of your own
#
# Any gpytorch kernel can replace the thesis's: here a Matern-5/2 kernel for each style's
# dynamics (wrapped in `DiscreteIntentionKernel`, so that every style keeps dynamics of its own)
# and a periodic-plus-RBF measurement kernel. Filtering, VB, GP-ADF and Monte-Carlo planning
# need the kernels' expectations under Gaussian inputs; kernels without closed forms are
# integrated at Gauss-Hermite nodes (`hgpdm_torch.quadrature`, accuracy on the API page).
# A custom kernel's model saves its state; loading rebuilds it with the same kernels.

# %%
from gpytorch.kernels import MaternKernel, PeriodicKernel, RBFKernel, ScaleKernel

from hgpdm_torch.kernels import DiscreteIntentionKernel


def kernels():
    dynamics = DiscreteIntentionKernel(ScaleKernel(MaternKernel(nu=2.5)), num_values=3)
    return dynamics, ScaleKernel(PeriodicKernel()) + ScaleKernel(RBFKernel())


dynamics, measurement = kernels()
custom = hg.HGPDM(data.sequences, data.labels, latent_dim=3,
                  transition_kernel=dynamics, measurement_kernel=measurement)
print(custom.fit(steps=20 if SMOKE else 80, warn=False))

# %% [markdown]
# The moment-matched prediction at an uncertain latent state against Monte Carlo of the GP's
# point predictions, then the style inferred online, one frame of each stream at a time:

# %%
post = custom.measurement_posterior()
x = torch.cat(custom.latent_sequences()).detach()
mu, Sigma = x[5], 0.01 * torch.cov(x.T)
with torch.no_grad():
    mean, cov, _ = post.predict_gaussian(mu, Sigma)  # 6 points per dim: 216 nodes
    with hg.settings.quadrature_points(16):  # a finer rule: 4,096 nodes
        fine = post.predict_gaussian(mu, Sigma)[0]
    draws = mu + torch.randn(400_000, 3, dtype=mu.dtype) @ torch.linalg.cholesky(Sigma).T
    mc = post.predict(draws)[0]
print('largest difference of the mean from Monte Carlo:',
      f'default rule {(mean - mc.mean(0)).abs().max():.1e},',
      f'finer rule {(fine - mc.mean(0)).abs().max():.1e},',
      f'Monte-Carlo standard error {(mc.std(0) / 400_000 ** 0.5).max():.1e}')

online = hg.OnlineIntentionFilter(custom, batch_size=len(data.sequences))
frames = torch.stack([s[:25] for s in data.sequences])
for t in range(frames.shape[1]):
    belief = online.update(frames[:, t])
print('inferred', belief.prob.argmax(-1).tolist())
print('true    ', data.labels.tolist())

path = pathlib.Path(tempfile.mkdtemp()) / 'custom.pt'
custom.save(path)
dynamics, measurement = kernels()
again = hg.load_model(path, model=hg.HGPDM(data.sequences, data.labels, latent_dim=3,
                                           transition_kernel=dynamics,
                                           measurement_kernel=measurement))
assert again.loss().item() == custom.loss().item()
