"""Every figure ``hgpdm anticipation`` and ``hgpdm demo`` save is readable (issue 54, item 7): no
two tick labels drawn over each other, every label inside the picture, and the planners (LSPI,
MCP) coloured apart from the references. Synthetic tables, no simulation."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure

from hgpdm_torch.decision.sources import PLAYER_SOURCES
from hgpdm_torch.experiments import anticipation as ant
from hgpdm_torch.results import ResultTable


@pytest.fixture
def saved(monkeypatch) -> dict[str, Figure]:
    """The figures saved during the test, by file name."""
    figures: dict[str, Figure] = {}
    real = Figure.savefig

    def keep(self, fname, *args, **kwargs):
        figures[str(fname).rsplit("/", 1)[-1]] = self
        return real(self, fname, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", keep)
    return figures


def _labels(fig: Figure) -> tuple[list, list]:
    """``(text, window bbox)`` of every drawn tick label of the figure's 2-D axes, and of every
    title and axis label."""
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()

    def boxes(texts) -> list:
        return [(t.get_text(), t.get_window_extent(renderer)) for t in texts
                if t.get_visible() and t.get_text().strip()]  # fmt: skip

    ticks, names = [], boxes([fig._suptitle] if fig._suptitle else [])
    for ax in fig.axes:
        names += boxes([ax.title])
        if ax.name == "3d":  # projected ticks: matplotlib places them while drawing
            continue
        for axis in (ax.xaxis, ax.yaxis):
            low, high = sorted(axis.get_view_interval())
            pad = 1e-9 * max(1.0, abs(high - low))
            drawn = [label for loc, label in zip(axis.get_majorticklocs(),
                                                 axis.get_majorticklabels(), strict=True)
                     if low - pad <= loc <= high + pad]  # fmt: skip
            ticks += boxes(drawn)
            names += boxes([axis.label])
    return ticks, names


def assert_readable(fig: Figure) -> None:
    """No two tick labels overlap (by more than a pixel each way), and no tick label, title or
    axis label is cut off at the figure's edge."""
    ticks, names = _labels(fig)
    assert ticks
    clashes = []
    for i, (text_a, a) in enumerate(ticks):
        for text_b, b in ticks[i + 1 :]:
            width = min(a.x1, b.x1) - max(a.x0, b.x0)
            height = min(a.y1, b.y1) - max(a.y0, b.y0)
            if width > 1 and height > 1:
                clashes.append((text_a, text_b))
    assert clashes == [], f"tick labels drawn over each other: {clashes}"
    frame = fig.bbox
    outside = [t for t, b in ticks + names if b.x0 < frame.x0 - 1 or b.x1 > frame.x1 + 1
               or b.y0 < frame.y0 - 1 or b.y1 > frame.y1 + 1]  # fmt: skip
    assert outside == [], f"labels cut off: {outside}"


def _grey(colour) -> bool:
    rgb = to_rgb(colour)
    return max(rgb) - min(rgb) < 0.1


def assert_planners_stand_out(fig: Figure, names: list[str]) -> None:
    """The bars of LSPI and MCP (drawn in the table's order) have colours of their own: not
    grey, and none of the references' colours."""
    (ax,) = [ax for ax in fig.axes if len(ax.patches) >= len(names)]
    colour = {n: to_rgb(p.get_facecolor()) for n, p in zip(names, ax.patches, strict=False)}
    planners = [colour["LSPI"], colour["MCP"]]
    assert planners[0] != planners[1]
    assert not any(_grey(c) for c in planners), colour
    references = [c for n, c in colour.items() if not n.startswith(("LSPI", "MCP"))]
    assert references and not any(c in planners for c in references), colour


def _fig6_fig7(n: int = 200) -> tuple[ResultTable, ResultTable]:
    """Tables shaped like ``hgpdm anticipation --full``'s: 15 methods, four episode counts."""
    methods = ant._methods(PLAYER_SOURCES)
    fig6 = ResultTable("Fig. 4.6", ["method", "returns", "SEM", "rate"], meta={"valid trials": n})
    for k, m in enumerate(methods):
        returns = n * (0.3 + 0.04 * k)
        fig6.add(method=m, returns=returns, SEM=2.0, rate=returns / n)
    fig7 = ResultTable("Fig. 4.7", ["episodes", "LSPI", "LSPI SEM", "MCP", "MCP SEM"])
    for e in (1, 2, 5, 10):
        fig7.add(**{"episodes": e, "LSPI": 100 + e, "LSPI SEM": 3, "MCP": 110 + e, "MCP SEM": 2})
    return fig6, fig7


def test_anticipation_figures_are_readable(saved, tmp_path):
    """``fig4_6_returns.png`` drew its 15 labels over each other, with LSPI and MCP grey (16
    rows with the ProMP belief)."""
    fig6, fig7 = _fig6_fig7()
    assert len(fig6.rows) >= 15
    paths = ant.plot_results(fig6, fig7, tmp_path)
    assert sorted(p.name for p in paths) == sorted(saved)
    assert_readable(saved["fig4_6_returns.png"])
    assert_planners_stand_out(saved["fig4_6_returns.png"], fig6.column("method"))
    assert_readable(saved["fig4_7_sample_efficiency.png"])


def _demo_result():
    """A :class:`DemoResult` shaped like ``hgpdm demo``'s, with one made-up rally."""
    pytest.importorskip("sapien")
    from hgpdm_torch.experiments import demo
    from hgpdm_torch.experiments.intervals import return_rate_interval
    from hgpdm_torch.robots.table_tennis.strokes import StrokeOutcome

    players = [demo.BLIND, demo.FIXED_TIME, "LSPI", "MCP", "LSPI (linear-iddm belief)",
               "LSPI (gp-iddm belief)", "MCP (oracle belief)",
               "oracle (best movement and time per stroke)",
               "best blind (after the fact)"]  # fmt: skip
    n = 300
    table = ResultTable(
        "hgpdm demo: anticipatory table tennis, 300 test rallies (3-fold cross-fitting over 300 "
        "of 380 strokes)",
        ["player", "returns", "rate", "95% low", "95% high", "played in"],
    )
    for k, p in enumerate(players):
        won = 120 + 15 * k
        low, high = return_rate_interval(won, n)
        table.add(**{"player": p, "returns": won, "rate": won / n, "95% low": low,
                     "95% high": high, "played in": "SAPIEN"})  # fmt: skip
    meta = {}
    for other in (demo.BLIND, demo.FIXED_TIME):
        meta.update({f"MCP - {other}": 0.1, f"MCP - {other} 95% low": 0.02,
                     f"MCP - {other} 95% high": 0.18})  # fmt: skip
    t = np.linspace(0, 1, 30)[:, None]
    ball = np.hstack([0.3 + 0 * t, 2.5 - 3.5 * t, 1.0 + 0.2 * t])
    outcome = StrokeOutcome(True, True, np.array([0.2, 1.0]), 0.1, ball + 0.05, ball,
                            np.zeros((0, 7)))  # fmt: skip
    rally = demo.Rally(0, 0.3, "forehand", -0.24, outcome)
    grid = torch.linspace(-1.2, 1.2, 25)
    probs = torch.softmax(-((grid - 0.3) ** 2)[None, None, :].repeat(1, 5, 1) * 4, -1)
    beliefs = {"linear-iddm": probs, "gp-iddm": probs, "oracle": probs}
    return players, demo.DemoResult(table, [rally], grid, (-0.32, -0.24, -0.16, -0.08, 0.0),
                                    probs, meta, {}, beliefs, ["linear-iddm"])  # fmt: skip


def test_demo_figures_are_readable(saved, tmp_path):
    """``return_rates.png`` drew its last three labels over each other."""
    from hgpdm_torch.experiments.demo import plot_demo

    players, result = _demo_result()
    paths = plot_demo(result, tmp_path)
    assert sorted(p.name for p in paths) == sorted(saved) == ["rally.png", "return_rates.png"]
    assert_readable(saved["return_rates.png"])
    assert_planners_stand_out(saved["return_rates.png"], players)
    assert_readable(saved["rally.png"])
