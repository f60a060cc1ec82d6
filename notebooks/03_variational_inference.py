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
# # 03 - Variational Bayes inference in the H-GPDM (thesis Sec. 2.3)
#
# Given a fitted H-GPDM and a short window of new observations, Algorithm 2.2 fits a mean-field
# Gaussian q(x_{1:T}) for every candidate style g and compares the maximised free energies F(q, g)
# (Eq. 13), the approximate log evidence log p(z_{1:T} | g). This notebook
#
# 1. fits an H-GPDM to synthetic movements with three planted styles,
# 2. recognises the style of held-out windows and forecasts the next frame (VB vs MAP),
# 3. recovers missing frames inside a window (H-GPDM vs GPDM, Fig. 2.3),
# 4. prints the table of the experiment `hgpdm_torch.experiments.style_recognition`.
#
# Under `HGPDM_SMOKE=1` everything runs at small sizes. Every MAP fit here runs a budget of 60
# L-BFGS steps, as the experiment's tables do: the objective keeps falling slowly far beyond it
# (notebook 01), so no fit meets the convergence criterion; each `FitResult` says so (printed below,
# and in `table.meta["fits"]` for the experiment's own fits), and its warning is switched off.

# %%
import os
import time
import warnings

import matplotlib.pyplot as plt
import torch

from hgpdm_torch.datasets import styled_movements
from hgpdm_torch.experiments import style_recognition as sr
from hgpdm_torch.fitting import ConvergenceWarning
from hgpdm_torch.inference.map import MAPInference
from hgpdm_torch.inference.variational import VariationalInference
from hgpdm_torch.models import HGPDM

torch.set_default_dtype(torch.float64)
SMOKE = os.environ.get("HGPDM_SMOKE", "0") == "1"
length = 30 if SMOKE else 40

# %% [markdown]
# ## 1. Data and model
#
# Train and test sequences come from **one** generated set (a held-out split): the generator draws
# its observation map from the seed, so a set drawn with another seed would have another map.

# %%
train, test = styled_movements(3, 4, length, 12, seed=0).split(0.25, seed=0)
model = HGPDM(train.sequences, train.labels, 3)
print(model.fit(60, warn=False))
vb = VariationalInference(model)
print("training frames N =", model.observations.shape[0], "| test sequences:", len(test))

# %% [markdown]
# ## 2. One window: the free energy per style
#
# `infer` runs, for all K styles at once: a nearest-frame start per style, Levenberg-Marquardt to
# the MAP states, the mean-field Laplace covariances Sigma_t = (Lambda_tt)^-1 (the optimum of F to
# second order), and the closed-form F. Without the Laplace step, L-BFGS on F from the GP-RTSS
# smoother stalls far below the optimum (`newton_steps=0`), which is what made the earlier
# recognition fail.

# %%
z = test.sequences[1][6:11]
res = vb.infer(z)
stalled = vb.infer(z, newton_steps=0, steps=20, init="smoother")
fig, ax = plt.subplots(1, 2, figsize=(9, 3))
ax[0].bar(range(3), res.log_evidence, label="Laplace start")
ax[0].plot(range(3), stalled.log_evidence, "rx", label="L-BFGS only (20 it.)")
ax[0].set(xlabel="style g", ylabel="F(q, g)", title=f"true style {int(test.labels[1])}")
ax[0].legend()
ax[1].bar(range(3), res.posterior)
ax[1].set(xlabel="style g", ylabel="p(g | z)", title="posterior over styles")
plt.tight_layout()

# %% [markdown]
# ## 3. Sliding windows: recognition and next-frame forecasts, VB vs MAP

# %%
z, nxt, y = [], [], []
for seq, label in zip(test.sequences, test.labels, strict=True):
    for i in range(0, seq.shape[0] - 5, 3):
        z.append(seq[i : i + 5])
        nxt.append(seq[i + 5])
        y.append(int(label))
z, nxt, y = torch.stack(z), torch.stack(nxt), torch.tensor(y)
for name, inf in (("VB", vb), ("MAP", MAPInference(model))):
    start = time.perf_counter()
    mean, var, r = inf.forecast(z)
    ms = 1e3 * (time.perf_counter() - start) / len(z)
    acc = float((r.g_ml == y).double().mean())
    rmse = float((mean - nxt).pow(2).mean().sqrt())
    print(f"{name}: {len(z)} windows, accuracy {acc:.3f}, forecast RMSE {rmse:.4f}, "
          f"{ms:.0f} ms/window")

# %%
mean, var, r = vb.forecast(z)
fig, ax = plt.subplots(figsize=(8, 3))
ax.plot(nxt[:, 0], "k.", label="next frame (truth)")
ax.errorbar(range(len(z)), mean[:, 0], 2 * var[:, 0].sqrt(), fmt="C0_", label="VB forecast +- 2 sd")
ax.set(xlabel="window", ylabel="channel 0")
ax.legend()
plt.show()

# %% [markdown]
# ## 4. Gap recovery (Fig. 2.3): H-GPDM vs GPDM on two-style data

# %%
import tempfile
from pathlib import Path

from IPython.display import Image

path = Path(tempfile.mkdtemp()) / "gap_recovery.png"
with warnings.catch_warnings():  # 60-step budgets (above)
    warnings.simplefilter("ignore", ConvergenceWarning)
    rmse = sr.gap_recovery_figure(path, fit_steps=60)
print("recovery RMSE over all test windows:", rmse)
Image(str(path))

# %% [markdown]
# ## 5. The experiment table (Tables 2.1-2.4 layout), synthetic data

# %%
with warnings.catch_warnings():  # 60-step budgets (above); each FitResult in table.meta["fits"]
    warnings.simplefilter("ignore", ConvergenceWarning)
    table = sr.style_recognition(("synthetic",), lengths=(5,) if SMOKE else (5, 10),
                                 fit_steps=60)
print(table.to_markdown())

# %% [markdown]
# ## 6. New recordings off the training manifold
#
# A new trial of a person rarely lies exactly on the poses the model was trained on: it deviates by
# a posture offset that persists from frame to frame, and the GPDM's white measurement noise forgets
# it. Two options help (on real CMU walks they turn a forecast that loses to ridge regression into
# one that beats it; docs, Walkers):
#
# - `forecast(window, residual="ar1")` carries the window's deviation from the model's
#   reconstruction forward as an AR(1) process, with its coefficient estimated from the window
#   itself;
# - `back_constraint="kernel"` makes the latent states a smooth map of the observations, X = f(Z),
#   so similar poses get similar latent positions.
#
# Below, the test windows are shifted by a small persistent offset (0.1 sd per channel).

# %%
signs = torch.randn(z.shape[-1], generator=torch.Generator().manual_seed(0)).sign()
offset = 0.1 * model.observations.std(0) * signs
shifted, target = z + offset, nxt + offset
bc = HGPDM(train.sequences, train.labels, 3, back_constraint="kernel")
print(bc.fit(60, warn=False))
for name, m in (("free latents", model), ("back-constrained", bc)):
    inf = VariationalInference(m)
    for residual in (None, "ar1"):
        mean, _, _ = inf.forecast(shifted, residual=residual)
        rmse = float((mean - target).pow(2).mean().sqrt())
        print(f"{name:17s} residual={residual!s:5s} next-frame RMSE {rmse:.4f}")
print("repeat last frame", float((shifted[:, -1] - target).pow(2).mean().sqrt()))
