"""Dataset helpers that must not return a silently unusable result (issue 54): a train/test
split with an empty (or style-less) training part, and BasicMotions' frame step."""

from __future__ import annotations

import pytest

from hgpdm_torch.datasets import load_basic_motions, styled_movements, targeted_movements


def test_split_of_two_sequences_keeps_one_to_train_on():
    """The finding: ``split(0.5)`` of two sequences returned an empty training set."""
    train, test = targeted_movements(num=2, length=5).split(0.5)
    assert len(train) == len(test) == 1
    train, test = targeted_movements(num=2, length=5).split(0.9)  # rounds to 2: one stays
    assert len(train) == len(test) == 1


def test_every_style_is_in_both_parts():
    data = styled_movements(num_styles=3, per_style=2, length=5)
    for fraction in (0.1, 0.5, 0.9):
        train, test = data.split(fraction)
        assert sorted(train.labels.tolist()) == sorted(test.labels.tolist()) == [0, 1, 2]
    # the usual case is unchanged: round(0.34 * 6) = 2 of each style to test
    train, test = styled_movements(3, 6, 5, 6).split(0.34)
    assert train.labels.bincount().tolist() == [4, 4, 4] and len(test) == 6


def test_split_refuses_what_cannot_be_split():
    with pytest.raises(ValueError, match=r"at least 2 sequences of every style .* style 0 has 1"):
        styled_movements(num_styles=2, per_style=1, length=5).split(0.5)
    with pytest.raises(ValueError, match=r"split needs at least 2 sequences, got 1"):
        targeted_movements(num=1, length=5).split(0.5)
    with pytest.raises(ValueError, match="test_fraction"):
        targeted_movements(num=4, length=5).split(1.0)


@pytest.mark.parametrize("subsample", [0, -1, 2.0, True])
def test_basic_motions_frame_step_is_checked_first(subsample):
    with pytest.raises(ValueError, match=r"subsample must be an int >= 1"):
        load_basic_motions(subsample)
