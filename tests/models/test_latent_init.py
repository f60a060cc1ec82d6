"""supervised_init: PLS initial latents keep a low-variance direction that carries the intention."""

from __future__ import annotations

import pytest
import torch

from hgpdm_torch.models import supervised_init


def test_supervised_init_keeps_a_low_variance_target_direction(generator):
    # the target sits in a low-variance feature next to a high-variance nuisance one: the leading
    # PCA direction misses it, the PLS init's first latent recovers it
    n, T = 30, 5
    g = torch.rand(n, generator=generator) * 2 - 1
    nuisance = 10.0 * torch.randn(n, T, 1, generator=generator)
    signal = 0.1 * g[:, None, None] + 0.01 * torch.randn(n, T, 1, generator=generator)
    obs = torch.cat([nuisance, signal, torch.randn(n, T, 1, generator=generator)], -1)
    x = supervised_init(obs, g, 2)
    assert x.shape == (n * T, 2)
    assert torch.allclose(x.std(0), torch.ones(2))
    frames_g = g.repeat_interleave(T)
    corr = torch.corrcoef(torch.stack([x[:, 0], frames_g]))[0, 1]
    assert corr.abs() > 0.9
    centred = obs.reshape(n * T, 3) - obs.reshape(n * T, 3).mean(0)
    pc1 = centred @ torch.linalg.svd(centred, full_matrices=False)[2][0]
    assert torch.corrcoef(torch.stack([pc1, frames_g]))[0, 1].abs() < 0.5


def test_supervised_init_rejects_bad_input():
    obs = torch.zeros(4, 3, 2)
    with pytest.raises(ValueError, match="latent_dim"):
        supervised_init(obs, torch.zeros(4), 3)
    with pytest.raises(ValueError, match="targets"):
        supervised_init(obs, torch.zeros(5), 1)
