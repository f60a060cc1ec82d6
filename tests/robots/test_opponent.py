"""Tests of the simulated opponent: physical consistency, informative but noisy observations."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

from hgpdm_torch.robots.table_tennis import ball as B
from hgpdm_torch.robots.table_tennis import geometry as geo
from hgpdm_torch.robots.table_tennis import opponent as O


@pytest.fixture(scope="module")
def strokes() -> O.Strokes:
    return O.sample_strokes(90, generator=torch.Generator().manual_seed(7))


def test_shapes_and_times(strokes: O.Strokes) -> None:
    assert strokes.obs.shape == (90, 6, 15)
    assert strokes.feature_names == O.FEATURE_NAMES and len(O.FEATURE_NAMES) == 15
    torch.testing.assert_close(
        strokes.obs_times, torch.tensor([-0.4, -0.32, -0.24, -0.16, -0.08, 0.0])
    )
    assert strokes.racket.pos.shape == (90, strokes.racket.times.shape[0], 3)
    assert bool((strokes.targets.abs() <= 1.5).all())


def test_returned_ball_crosses_the_hitting_plane_at_targets(strokes: O.Strokes) -> None:
    after = strokes.ball_after_hit
    t, at, valid = B.predict_plane_crossing(after, geo.HITTING_PLANE_Y)
    assert bool(valid.all())
    torch.testing.assert_close(at.pos[:, 0], strokes.targets, atol=1e-9, rtol=0)
    traj = B.simulate(after, float(t.max()), 0.005)
    assert bool(B.is_legal_return(traj, side=geo.ROBOT_SIDE).all())
    # execution noise moves the ball off the aimed target, but not far
    err = (strokes.targets - strokes.final_aim).abs()
    assert 0 < float(err.mean()) < 0.1


def test_racket_at_contact_produces_the_returned_ball(strokes: O.Strokes) -> None:
    before, after, racket = strokes.ball_before_hit, strokes.ball_after_hit, strokes.racket
    torch.testing.assert_close(racket.pos[:, -1], before.pos, atol=1e-12, rtol=0)
    vel, spin = B.racket_contact(before.vel, before.spin, racket.vel[:, -1], racket.normal[:, -1])
    torch.testing.assert_close(vel, after.vel, atol=1e-9, rtol=0)
    torch.testing.assert_close(spin, after.spin, atol=1e-7, rtol=0)
    # the reported racket velocity is the derivative of its path (central differences)
    dt = float(racket.times[1] - racket.times[0])
    fd = (racket.pos[:, 2:] - racket.pos[:, :-2]) / (2 * dt)
    scale = float(racket.vel.abs().max())
    assert float((fd - racket.vel[:, 1:-1]).abs().max()) < 0.02 * scale
    torch.testing.assert_close(
        racket.normal.norm(dim=-1), torch.ones_like(racket.times).expand(90, -1)
    )


# the GPR baseline drives irrelevant inputs' length scales to their bound, as it should
@pytest.mark.filterwarnings("ignore:The optimal value found:sklearn.exceptions.ConvergenceWarning")
def test_observations_inform_but_do_not_determine_the_target(strokes: O.Strokes) -> None:
    # the thesis' GPR baseline: last two observations -> target
    x = strokes.obs[:, -2:].reshape(90, -1).numpy()
    x = (x - x[:60].mean(0)) / x[:60].std(0)
    y = strokes.targets.numpy()
    kernel = ConstantKernel() * RBF(np.ones(x.shape[1])) + WhiteKernel(0.01)
    gp = GaussianProcessRegressor(kernel, normalize_y=True, random_state=0).fit(x[:60], y[:60])
    mae = np.abs(gp.predict(x[60:]) - y[60:]).mean()
    median = np.abs(np.median(y[:60]) - y[60:]).mean()
    assert mae < 0.5 * median
    assert mae > 0.01


def test_styles_timing_and_late_changes_vary(strokes: O.Strokes) -> None:
    assert set(strokes.style.tolist()) == {0, 1}
    # ball_side rule: forehand on the player's right (x < 0.05)
    x = strokes.ball_before_hit.pos[:, 0]
    assert torch.equal(strokes.style, (x >= 0.05).long())
    assert float(strokes.swing_duration.std()) > 0.01
    assert float(strokes.hit_time.max() - strokes.hit_time.min()) > 0.05
    late = strokes.late_change
    assert 0 < int(late.sum()) < 90
    assert bool((strokes.final_aim[late] * strokes.intended[late] < 0).all())
    torch.testing.assert_close(strokes.final_aim[~late], strokes.intended[~late])
    assert bool((strokes.switch_time[late] < 0).all())


def test_seeds_reproduce() -> None:
    cfg = O.OpponentConfig(late_change_prob=0.5)
    a = O.sample_strokes(2, config=cfg, generator=torch.Generator().manual_seed(1))
    b = O.sample_strokes(2, config=cfg, generator=torch.Generator().manual_seed(1))
    c = O.sample_strokes(2, config=cfg, generator=torch.Generator().manual_seed(2))
    assert torch.equal(a.obs, b.obs) and torch.equal(a.targets, b.targets)
    assert not torch.equal(a.obs, c.obs)


@pytest.fixture
def float32_default():
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float32)
    yield
    torch.set_default_dtype(old)


def test_every_seed_gives_legal_strokes_under_float32_default(float32_default) -> None:
    # Seeds and sizes that used to fail (n=3 seed 0 among them); extreme targets included.
    for n, seed in ((3, 0), (1, 1), (2, 2), (1, 3), (2, 4), (1, 5)):
        s = O.sample_strokes(n, generator=torch.Generator().manual_seed(seed))
        assert s.obs.dtype == torch.float64 and s.obs.shape[0] == n
        assert bool(torch.isfinite(s.obs).all())
        _, at, valid = B.predict_plane_crossing(s.ball_after_hit, geo.HITTING_PLANE_Y)
        assert bool(valid.all())
        torch.testing.assert_close(at.pos[:, 0], s.targets, atol=1e-9, rtol=0)
    wide = O.sample_strokes(
        2,
        config=O.OpponentConfig(late_change_prob=0.0),
        targets=[-1.2, 1.2],
        generator=torch.Generator().manual_seed(0),
    )
    assert float((wide.targets - torch.tensor([-1.2, 1.2], dtype=torch.float64)).abs().max()) < 0.15


def test_given_targets_are_kept() -> None:
    targets = torch.tensor([-1.1, 0.0, 1.2])
    cfg = O.OpponentConfig(late_change_prob=0.0)
    s = O.sample_strokes(3, config=cfg, targets=targets, generator=torch.Generator().manual_seed(4))
    torch.testing.assert_close(s.intended, targets)
    assert float((s.targets - targets).abs().max()) < 0.15


def test_bad_input_raises() -> None:
    with pytest.raises(ValueError, match="n must"):
        O.sample_strokes(0)
    with pytest.raises(ValueError, match="targets"):
        O.sample_strokes(2, targets=[0.0, 1.5])
    with pytest.raises(ValueError, match="targets"):
        O.sample_strokes(2, targets=[0.0])
    with pytest.raises(ValueError, match="late_change_prob"):
        O.OpponentConfig(late_change_prob=1.5)
    with pytest.raises(ValueError, match="style_rule"):
        O.OpponentConfig(style_rule="left")
    with pytest.raises(ValueError, match="bounce_y"):
        O.OpponentConfig(bounce_y=(-0.5, -1.0))
    with pytest.raises(ValueError, match="window"):
        O.OpponentConfig(n_obs=12)
    with pytest.raises(TypeError, match="config"):
        O.sample_strokes(1, config={"n_obs": 6})
