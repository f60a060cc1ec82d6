"""The folds, the held-out loop and the choice that every cross-validated selection uses."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from sklearn.model_selection import GroupKFold, KFold

from hgpdm_torch.crossval import (
    best_index,
    checked_splits,
    contiguous_folds,
    held_out,
    interleaved_folds,
)


@pytest.mark.parametrize(("num", "folds"), [(10, 3), (100, 3), (7, 2), (100, 5), (5, 5)])
def test_folds_partition_the_items(num, folds):
    for splits in (interleaved_folds(num, folds), contiguous_folds(num, folds)):
        assert len(splits) == folds
        held = sorted(j for _, test in splits for j in test)
        assert held == list(range(num))  # every item held out exactly once
        for train, test in splits:
            assert sorted(train + test) == list(range(num)) and not set(train) & set(test)
    # the contiguous runs are torch.tensor_split's, the interleaved folds j mod k
    runs = [t.tolist() for t in torch.arange(num).tensor_split(folds)]
    assert [test for _, test in contiguous_folds(num, folds)] == runs
    for k, (_, test) in enumerate(interleaved_folds(num, folds)):
        assert test == [j for j in range(num) if j % folds == k]


@pytest.mark.parametrize("folds", [1, 11, 2.0, True, None])
def test_bad_fold_counts_are_refused(folds):
    with pytest.raises(ValueError, match=r"folds must be an int in \[2, 10\]"):
        interleaved_folds(10, folds)
    with pytest.raises(ValueError, match="folds"):
        contiguous_folds(10, folds)


def test_checked_splits_refuse_a_group_on_both_sides_and_an_untrained_class():
    groups = np.array([0, 0, 1, 1, 2, 2])
    assert len(checked_splits(GroupKFold(3), groups)) == 3
    with pytest.raises(ValueError, match="puts groups .* in both"):
        checked_splits(KFold(2), groups)  # items 2 and 3 (group 1) fall apart
    labels = np.array([0, 0, 0, 0, 1, 1])  # class 1 only in group 2
    with pytest.raises(ValueError, match=r"labels \[1\] occur in the test part"):
        checked_splits(GroupKFold(3), groups, labels, discrete=True)
    checked_splits(GroupKFold(3), groups, labels, discrete=False)  # a continuous g may


def test_held_out_runs_every_fold_in_order_and_names_a_failing_one():
    splits = interleaved_folds(6, 3)
    assert held_out(splits, lambda k, train, test: (k, sum(test))) == [(0, 3), (1, 5), (2, 7)]
    data = [("a", 1), ("b", 2)]  # folds that carry their own data
    assert held_out(data, lambda k, name, n: name * n) == ["a", "bb"]

    def fail_on_second(k, train, test):
        if k == 1:
            raise RuntimeError("boom")
        return k

    with pytest.raises(RuntimeError, match="boom") as info:
        held_out(splits, fail_on_second, context="candidate x")
    assert info.value.__notes__ == ["cross-validation: candidate x, fold 1"]


def test_best_index_takes_the_first_best_and_refuses_nan():
    assert best_index([3.0, 1.0, 1.0, 2.0]) == 1
    assert best_index([3.0, 1.0, 3.0], greater_is_better=True) == 0
    with pytest.raises(ValueError, match="NaN"):
        best_index([1.0, float("nan")])
    with pytest.raises(ValueError, match="at least one"):
        best_index([])
