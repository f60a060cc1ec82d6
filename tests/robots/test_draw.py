"""Drawings: the arm is drawn where forward kinematics puts it; bad input raises."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pytest
import torch

from hgpdm_torch.robots.table_tennis import geometry as geo
from hgpdm_torch.robots.table_tennis.draw import (
    draw_arm,
    draw_stroke,
    draw_table,
    plot_hitting_regions,
)
from hgpdm_torch.robots.table_tennis.strokes import StrokeOutcome
from hgpdm_torch.robots.wam import RACKET_RADIUS, WAM

Q = np.array([0.3, 0.8, -0.2, 1.6, 0.1, -0.4, 0.2])


@pytest.fixture
def ax3d():
    fig = plt.figure()
    yield fig.add_subplot(projection="3d")
    plt.close(fig)


def _lines(ax) -> list[np.ndarray]:
    return [np.stack(line.get_data_3d(), -1) for line in ax.get_lines()]


def test_arm_follows_forward_kinematics(ax3d) -> None:
    wam = WAM()
    draw_arm(ax3d, wam, Q)
    lines = _lines(ax3d)
    pts = wam.frame_positions(torch.as_tensor(Q)).numpy()
    np.testing.assert_allclose(lines[0], pts[:-1], atol=1e-12)
    # the racket rim is a circle of the racket's radius around the FK racket centre, in its plane
    pose = wam.fk(torch.as_tensor(Q))
    rim = lines[-1]
    centre, normal = pose.position.numpy(), pose.normal.numpy()
    np.testing.assert_allclose(np.linalg.norm(rim - centre, axis=1), RACKET_RADIUS, atol=1e-12)
    np.testing.assert_allclose((rim - centre) @ normal, 0.0, atol=1e-12)


def test_table_top_view() -> None:
    fig, ax = plt.subplots()
    draw_table(ax)
    outline = np.stack(ax.get_lines()[0].get_data(), -1)
    np.testing.assert_allclose(
        np.abs(outline).max(0), [geo.TABLE_HALF_WIDTH, geo.TABLE_HALF_LENGTH]
    )
    plane = np.stack(ax.get_lines()[-1].get_data(), -1)
    np.testing.assert_allclose(plane[:, 1], geo.HITTING_PLANE_Y)
    plt.close(fig)


def test_table_and_stroke(ax3d) -> None:
    draw_table(ax3d)
    table = _lines(ax3d)[0]
    assert np.allclose(table[:, 2], geo.TABLE_HEIGHT)
    assert np.isclose(np.abs(table[:, 0]).max(), geo.TABLE_HALF_WIDTH)
    s = 5
    path = np.linspace([0.0, -2.3, 0.8], [0.1, -2.1, 0.9], s)
    out = StrokeOutcome(
        success=True,
        hit=True,
        landing=np.array([0.1, 0.8]),
        t_hit=0.9,
        racket_path=path,
        ball_path=np.vstack([np.full((1, 3), np.nan), path[1:] + 0.01]),
        joint_path=np.tile(Q, (s, 1)),
    )
    n_before = len(ax3d.get_lines())
    draw_stroke(ax3d, out, WAM())
    assert len(ax3d.get_lines()) > n_before + 2  # ball, racket, arm and racket rim


def test_hitting_regions_plot() -> None:
    fig, ax = plt.subplots()
    centers = np.array([-0.6, 0.0, 0.6])
    rates = {"forehand": np.array([0.0, 0.5, 1.0]), "backhand": np.array([1.0, np.nan, 0.0])}
    plot_hitting_regions(ax, centers, rates, np.array([3, 0, 4]), start_time=-0.24)
    got = {line.get_label(): line.get_ydata() for line in ax.get_lines()}
    np.testing.assert_array_equal(got["forehand"], rates["forehand"])
    assert "240 ms" in ax.get_title()
    plt.close(fig)


def test_bad_input_raises(ax3d) -> None:
    fig, ax2d = plt.subplots()
    with pytest.raises(TypeError, match="3-D"):
        draw_arm(ax2d, WAM(), Q)
    with pytest.raises(ValueError, match="q must"):
        draw_arm(ax3d, WAM(), np.zeros(6))
    with pytest.raises(TypeError, match="outcome"):
        draw_stroke(ax3d, "stroke")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="unknown movement"):
        plot_hitting_regions(ax2d, np.zeros(2), {"lob": np.zeros(2)})
    with pytest.raises(ValueError, match="shape"):
        plot_hitting_regions(ax2d, np.zeros(2), {"middle": np.zeros(3)})
    plt.close(fig)
