"""Cross-validation over model options: against a hand-written loop, known winners, grouping,
bad input."""

from __future__ import annotations

import math
import statistics
from typing import Any

import numpy as np
import pytest
import torch
from sklearn.model_selection import GroupKFold, KFold, LeaveOneGroupOut

import hgpdm_torch as hg
from hgpdm_torch.datasets import styled_movements
from hgpdm_torch.inference.variational import VariationalInference
from hgpdm_torch.model_selection import forecast_rmse
from hgpdm_torch.models import GPDM, HGPDM
from hgpdm_torch.parallel import get_executor
from hgpdm_torch.results import ResultTable

# Two styles, three sequences each; person p performs sequences p and p + 3 (one of each style),
# so grouping by person keeps both styles in every training part.
PERSONS = [0, 1, 2, 0, 1, 2]
EPS = torch.finfo(torch.float64).eps


@pytest.fixture(scope="module")
def data():
    return styled_movements(num_styles=2, per_style=3, length=15, obs_dim=6, seed=0)


def spread_score(model: Any, test: list[torch.Tensor], labels: Any) -> float:
    """A cheap score that depends on the fit and on the test part: final loss per frame plus the
    test frames' mean squared distance from the training mean."""
    with torch.no_grad():
        loss = float(model.loss()) / model.observations.shape[0]
    return loss + float(torch.cat(test).sub(model.obs_mean).pow(2).mean())


class RandomStart(GPDM):
    """A GPDM with random initial latents and a legacy ``fit`` that returns a bare loss history
    (no optimisation: the tests of seeding and reporting need no real fit)."""

    def initial_latents(self, centred: torch.Tensor) -> torch.Tensor:
        return torch.randn(centred.shape[0], self.latent_dim, dtype=centred.dtype)

    def fit(self, steps: int = 100, **kwargs: Any) -> list[float]:
        return [2.0, 1.0]


def latent_sum(model: Any, test: list[torch.Tensor], labels: Any) -> float:
    return float(model.latent.detach().sum())


# ----------------------------------------------------------------- (1) an independent reference
def test_fold_scores_match_a_hand_written_loop(data):
    cv = hg.cross_validate(
        HGPDM,
        data.sequences,
        spread_score,
        labels=data.labels,
        groups=PERSONS,
        grid={"measurement": ["rbf", "linear"]},
        fixed={"latent_dim": 2},
        fit_steps=5,
        seed=3,
    )
    expected_scores, expected_reasons, expected_splits = [], [], []
    for measurement in ("rbf", "linear"):  # grid order
        scores, reasons = [], []
        logo = LeaveOneGroupOut().split(np.zeros((6, 1)), data.labels.numpy(), PERSONS)
        for train, test in logo:
            torch.manual_seed(3)
            model = HGPDM(
                [data.sequences[i] for i in train],
                data.labels[train],
                2,
                measurement=measurement,
            )
            fit = model.fit(steps=5, warn=False)
            scores.append(spread_score(model, [data.sequences[i] for i in test], None))
            reasons.append((fit.converged, fit.reason))
            if measurement == "rbf":
                expected_splits.append((train.tolist(), test.tolist()))
        expected_scores.append(scores)
        expected_reasons.append(reasons)

    assert cv.options == [{"measurement": "rbf"}, {"measurement": "linear"}]
    assert cv.splits == expected_splits
    # the same fits and scores in the same process, on the same shapes: the same rounding
    assert np.allclose(cv.fold_scores, expected_scores, rtol=1e-12, atol=0)
    got = [[(f["converged"], f["reason"]) for f in row] for row in cv.table.meta["fits"]]
    assert got == expected_reasons
    for row, scores, reasons in zip(cv.table.rows, expected_scores, expected_reasons, strict=True):
        assert row["score"] == pytest.approx(statistics.fmean(scores), rel=1e-12)
        assert row["sem"] == pytest.approx(statistics.stdev(scores) / math.sqrt(3), rel=1e-10)
        assert row["folds"] == 3
        assert row["not converged"] == sum(not c for c, _ in reasons)
    means = [statistics.fmean(s) for s in expected_scores]
    assert cv.best_score == pytest.approx(min(means), rel=1e-12)
    assert cv.best_options == cv.options[int(np.argmin(means))]
    assert cv.table.columns == ["measurement", "score", "sem", "folds", "not converged"]
    assert cv.table.meta["fixed"] == {"latent_dim": 2} and cv.table.meta["seed"] == 3


def test_seeded_random_init_legacy_fit_and_json(data, tmp_path):
    sequences = torch.stack(data.sequences)  # a [J, T, Dz] tensor works too
    torch.manual_seed(123)
    before = torch.rand(3)
    torch.manual_seed(123)
    cv = hg.cross_validate(
        RandomStart, sequences, latent_sum, grid={"latent_dim": [1, 2]}, splitter=GroupKFold(3)
    )
    assert torch.equal(torch.rand(3), before)  # the caller's random stream is untouched
    again = hg.cross_validate(
        RandomStart, sequences, latent_sum, grid={"latent_dim": [1, 2]}, splitter=GroupKFold(3)
    )
    assert again.fold_scores == cv.fold_scores
    for (train, _), value in zip(cv.splits, cv.fold_scores[1], strict=True):
        torch.manual_seed(0)
        assert value == latent_sum(RandomStart([data.sequences[i] for i in train], 2), [], None)
    other = hg.cross_validate(
        RandomStart, sequences, latent_sum, grid={"latent_dim": [1]}, splitter=GroupKFold(3), seed=1
    )
    assert other.fold_scores[0] != cv.fold_scores[0]
    # a fit that returns a bare history: convergence unknown, not counted as a failure
    assert cv.table.meta["fits"][0][0] == {"converged": None, "reason": None, "final_loss": 1.0}
    assert cv.table.column("not converged") == [0, 0]
    cv.table.to_json(tmp_path / "cv.json")
    assert ResultTable.from_json(tmp_path / "cv.json").rows == cv.table.rows


# ----------------------------------------------------------------- (2) the better option wins
def test_best_option_follows_the_score(data):
    def distance_to_two(model: Any, test: list[torch.Tensor], labels: Any) -> float:
        return abs(model.latent_dim - 2) + 0.01 * len(test)

    kw = dict(grid={"latent_dim": [1, 2, 3]}, splitter=GroupKFold(2))
    cv = hg.cross_validate(RandomStart, data.sequences, distance_to_two, **kw)
    assert cv.best_options == {"latent_dim": 2} and cv.best_score == pytest.approx(0.03)
    assert cv.table.column("score") == pytest.approx([1.03, 0.03, 1.03])
    assert cv.table.column("sem") == pytest.approx([0.0, 0.0, 0.0])
    worst = hg.cross_validate(
        RandomStart, data.sequences, distance_to_two, greater_is_better=True, **kw
    )
    assert worst.best_options == {"latent_dim": 1}  # first of the tied best


def test_cycle_needs_more_than_one_latent_dim(data):
    """Every style moves on a closed curve: a 1-D latent space cannot carry its dynamics (a
    state x maps to two different successors), so VB forecasts of held-out people are worse."""
    cv = hg.cross_validate(
        HGPDM,
        data.sequences,
        forecast_rmse(5, stride=5),
        labels=data.labels,
        groups=PERSONS,
        grid={"latent_dim": [1, 3]},
        splitter=GroupKFold(3),
        fit_steps=8,
    )
    assert cv.best_options == {"latent_dim": 3}
    one, three = cv.fold_scores
    assert all(a > b for a, b in zip(one, three, strict=True))  # worse for every held-out person


def test_forecast_rmse_matches_direct_vb_forecasts(data):
    model = GPDM(data.sequences[:4], 2)
    model.fit(steps=5, warn=False)
    test = data.sequences[4:]
    windows, targets = [], []
    for seq in test:
        for start in range(0, 15 - 4, 4):
            windows.append(seq[start : start + 4])
            targets.append(seq[start + 4])
    # The same work in both runs: 5 Levenberg-Marquardt steps per window. With the default 30,
    # a window stops after a step that gains < 1e-3 nats, and one window has a step gaining
    # 1.1e-3: the batch shape's rounding decides where it stops (7.6e-6 apart in the RMSE). In
    # the first 5 steps every accepted step gains >= 3.8 nats and every rejected one loses
    # >= 27 nats (|F| <= 4e4), so both runs accept and reject the same steps and none stops.
    steps = {"newton_steps": 5}
    mean = VariationalInference(model).forecast(torch.stack(windows), **steps)[0]
    expected = float((mean - torch.stack(targets)).pow(2).mean().sqrt())
    # Batches of 3 windows against all 6 at once: other BLAS kernels. The transition GP's
    # predictive variance cancels k(x, x) ~ 1 down to its noise (1e-4) through a solve with
    # K + noise I, to a relative eps * cond(K) * k(x, x) / noise (~1.6e-6 here); the LM steps
    # and the forecasts inherit that (measured: up to 3e-8 relative in the RMSE).
    trans = model.transition_posterior()
    kernel = trans.chol @ trans.chol.mT
    rel = EPS * float(torch.linalg.cond(kernel) * kernel.diagonal().max() / trans.noise)
    score = forecast_rmse(4, stride=4, batch_size=3, **steps)(model, test, None)
    assert score == pytest.approx(expected, rel=rel)
    with pytest.raises(ValueError, match="window=20"):
        forecast_rmse(20)(model, test, None)
    with pytest.raises(ValueError, match="window"):
        forecast_rmse(1)


# ----------------------------------------------------------------- (3) bad input
@pytest.mark.parametrize(
    "changes, error, match",
    [
        ({"model_class": "HGPDM"}, TypeError, "model_class"),
        ({"score": 1.0}, TypeError, "score"),
        ({"grid": {"latent_dims": [2]}}, ValueError, "unknown option 'latent_dims' in grid"),
        ({"fixed": {"measurment": "rbf"}}, ValueError, "unknown option 'measurment' in fixed"),
        ({"grid": {"intentions": [[0] * 4]}}, ValueError, "supplied by cross_validate"),
        ({"grid": {"latent_dim": []}}, ValueError, r"grid\['latent_dim'\] is empty"),
        ({"grid": {"measurement": "rbf"}}, TypeError, r"grid\['measurement'\]"),
        ({"grid": {"latent_dim": [2]}, "fixed": {"latent_dim": 2}}, ValueError, "both grid"),
        ({"fit_steps": 0}, ValueError, "fit_steps"),
        ({"fit_steps": -3}, ValueError, "fit_steps"),
        ({"fit_steps": 2.5}, ValueError, "fit_steps"),
        ({"fit_steps": True}, ValueError, "fit_steps"),
        ({"fit_kwargs": {"steps": 3}}, ValueError, "fit_steps"),
        ({"labels": None}, ValueError, "labels is required"),
        ({"labels": [0, 0, 1, 1]}, ValueError, r"labels must have one entry per sequence \(6\)"),
        ({"groups": [0, 1, 2]}, ValueError, r"groups must have one entry per sequence \(6\)"),
        ({"groups": [7] * 6}, ValueError, "at least 2 distinct groups"),
        ({"splitter": "logo"}, TypeError, "splitter"),
        pytest.param(
            {"splitter": KFold(3)},
            ValueError,
            "in both the training and the test part",
            marks=pytest.mark.filterwarnings("ignore:The groups parameter is ignored by KFold"),
        ),
        # grouping by style leaves the held-out style untrained
        (
            {"groups": [0, 0, 0, 1, 1, 1], "splitter": LeaveOneGroupOut()},
            ValueError,
            r"fold 0: labels \[0\] occur in the test part but not in the training part",
        ),
    ],
)
def test_bad_input_names_the_argument(data, changes, error, match):
    kwargs: dict[str, Any] = dict(
        model_class=HGPDM,
        sequences=data.sequences,
        score=spread_score,
        labels=data.labels,
        groups=PERSONS,
        grid={"latent_dim": [2]},
        splitter=GroupKFold(3),
        fit_steps=1,
    )
    kwargs.update(changes)
    with pytest.raises(error, match=match):
        hg.cross_validate(**kwargs)


def test_folds_on_local_processes_give_the_serial_table(data, monkeypatch):
    """cross_validate on 2 spawned processes (each fit seeded on its own, the workers with this
    process's thread count, so the same BLAS kernels): the same table, bit for bit."""
    kw = dict(labels=data.labels, groups=PERSONS, grid={"measurement": ["rbf", "linear"]},
              fixed={"latent_dim": 2}, fit_steps=5, seed=3)  # fmt: skip
    serial = hg.cross_validate(HGPDM, data.sequences, spread_score, **kw)
    monkeypatch.setenv("OMP_NUM_THREADS", str(torch.get_num_threads()))
    with get_executor(2) as pool:
        parallel = hg.cross_validate(HGPDM, data.sequences, spread_score, executor=pool, **kw)
    assert parallel.fold_scores == serial.fold_scores
    assert parallel.table.rows == serial.table.rows
    assert parallel.table.meta["fits"] == serial.table.meta["fits"]


def test_non_finite_or_non_numeric_score_names_options_and_fold(data):
    for value, error in ((float("nan"), ValueError), ("bad", TypeError)):
        with pytest.raises(error, match=r"options \{'latent_dim': 1\}, fold 0"):
            hg.cross_validate(
                RandomStart,
                data.sequences,
                lambda model, test, labels, value=value: value,
                grid={"latent_dim": [1]},
            )


class Tagged(HGPDM):
    """A subclass with its own keyword that forwards the rest to HGPDM and on to GPDM."""

    def __init__(self, sequences: Any, intentions: Any, *, tag: str = "a", **kwargs: Any) -> None:
        super().__init__(sequences, intentions, **kwargs)
        self.tag = tag


class StopHere(Exception):
    pass


def test_options_reach_base_classes_through_kwargs(data):
    seen = []

    def stop(model: Any, test: list[torch.Tensor], labels: Any) -> float:
        seen.append((model.tag, model.latent_dim, model.measurement, model.intention))
        raise StopHere

    with pytest.raises(StopHere) as info:
        hg.cross_validate(
            Tagged,
            data.sequences,
            stop,
            labels=data.labels,
            groups=PERSONS,
            grid={"tag": ["b"], "measurement": ["linear"]},
            fixed={"latent_dim": 1, "intention": "discrete"},
            fit_steps=1,
        )
    assert seen == [("b", 1, "linear", "discrete")]
    assert any("fold 0" in note for note in info.value.__notes__)
    with pytest.raises(ValueError, match="unknown option 'tags'"):
        hg.cross_validate(Tagged, data.sequences, stop, labels=data.labels, grid={"tags": ["b"]})


# ----------------------------------------------------------------- (4) grouping
@pytest.mark.parametrize("splitter", [LeaveOneGroupOut(), GroupKFold(2)])
def test_no_group_on_both_sides_of_a_fold(data, splitter):
    groups = np.array(["ann", "bob", "cy", "ann", "bob", "cy"])
    seen = []

    def record(model: Any, test: list[torch.Tensor], labels: Any) -> float:
        def index(seq: torch.Tensor) -> int:
            return next(j for j, s in enumerate(data.sequences) if torch.equal(s, seq))

        train = [index(s) for s in model.sequences()]
        assert torch.equal(model.intention_codes(), data.labels[train])
        tested = [index(s) for s in test]
        assert torch.equal(labels, data.labels[tested])
        seen.append((train, tested))
        return 0.0

    cv = hg.cross_validate(
        HGPDM,
        data.sequences,
        record,
        labels=data.labels,
        groups=groups,
        splitter=splitter,
        fixed={"latent_dim": 1},
        fit_steps=1,
    )
    assert [(sorted(a), sorted(b)) for a, b in seen] == [(a, b) for a, b in cv.splits]
    for train, test in seen:
        assert not set(groups[train]) & set(groups[test])
        assert sorted(train + test) == list(range(6))
    assert sorted(j for _, test in seen for j in test) == list(range(6))
