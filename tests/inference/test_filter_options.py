"""The online filter's choices in groups (``inference/intention/options.py``): a group object and
its flat keywords make the same filter, bit for bit; mixing the two for one group is refused."""

from __future__ import annotations

import pytest
import torch

from hgpdm_torch.inference import OnlineIntentionFilter
from hgpdm_torch.inference.intention import (
    BeliefUpdate,
    Evidence,
    FilterOptions,
    ObservationPolicy,
    StatePrior,
    TransitionPath,
)

GRID = torch.linspace(-1.0, 1.0, 5)


@pytest.fixture(scope="module")
def model(continuous_iddm):
    return continuous_iddm


@pytest.fixture(scope="module")
def z(model) -> torch.Tensor:
    """``[2, 6, Dz]``: two streams of training frames."""
    seqs = model.sequences()
    return torch.stack([seqs[0][:6], seqs[1][2:8]])


def beliefs(f: OnlineIntentionFilter, z: torch.Tensor) -> torch.Tensor:
    return torch.stack([f.update(z[:, t]).log_prob for t in range(z.shape[1])])


FLAT_AND_GROUPED = [
    ({"forgetting": 0.1, "temperature": 2.0}, {"belief": BeliefUpdate(0.1, 2.0)}),
    (
        {"evidence": "bound", "relinearize": True},
        {"evidence": Evidence("bound", relinearize=True)},
    ),
    ({"transition": "generic"}, {"transition": TransitionPath("generic")}),
    ({"outlier_sd": 5.0}, {"observations": ObservationPolicy(outlier_sd=5.0)}),
    ({"inducing": 30}, {"transition": TransitionPath(inducing=30)}),
]


@pytest.mark.parametrize(("flat", "grouped"), FLAT_AND_GROUPED)
def test_a_group_object_and_its_flat_keywords_make_the_same_filter(model, z, flat, grouped):
    a = OnlineIntentionFilter(model, GRID, batch_size=2, **flat)
    b = OnlineIntentionFilter(model, GRID, batch_size=2, **grouped)
    assert a.options == b.options
    assert torch.equal(beliefs(a, z), beliefs(b, z))
    # and differs from the defaults (the option is not ignored)
    default = OnlineIntentionFilter(model, GRID, batch_size=2)
    assert default.options != a.options


def test_array_valued_options_compare_by_value(model, z):
    # a prior and a first-state mean as tensors: equal groups, the same filter
    prior = torch.tensor([0.1, 0.2, 0.3, 0.2, 0.2], dtype=torch.float64)
    mu0 = model.latent.detach().mean(0)
    a = OnlineIntentionFilter(model, GRID, batch_size=2, prior=prior, mu0=mu0)
    b = OnlineIntentionFilter(
        model, GRID, batch_size=2, belief=BeliefUpdate(prior=prior.tolist()),
        state_prior=StatePrior(mu0=mu0.clone()),
    )  # fmt: skip
    assert a.options == b.options
    assert torch.equal(beliefs(a, z), beliefs(b, z))
    assert BeliefUpdate(prior=prior) != BeliefUpdate(prior=prior.flip(0))
    assert StatePrior(mu0=mu0) != StatePrior(mu0=mu0[:2])  # another shape
    assert BeliefUpdate() != "BeliefUpdate()"


def test_the_options_make_another_filter_with_the_same_choices(model, z):
    first = OnlineIntentionFilter(
        model, GRID, batch_size=2, forgetting=0.3, evidence="bound", outlier_sd=20.0
    )
    again = OnlineIntentionFilter(model, GRID, batch_size=2, **vars(first.options))
    assert again.options == first.options
    assert torch.equal(beliefs(first, z), beliefs(again, z))
    # the flat keywords land in their groups
    assert first.options.belief == BeliefUpdate(forgetting=0.3, temperature=1.0)
    assert first.options.evidence == Evidence("bound", mixing="grid", relinearize=False)
    assert first.options.state_prior.kind == "marginal"
    assert first.options.observations == ObservationPolicy(outlier_sd=20.0, strict=False)
    assert not hasattr(first, "forgetting")  # the groups alone hold the choices
    assert FilterOptions() == OnlineIntentionFilter(model, GRID).options


def test_a_group_and_its_keywords_together_are_refused(model):
    both = r"belief=BeliefUpdate\(...\) or the keywords \['forgetting'\]"
    with pytest.raises(ValueError, match=both):
        OnlineIntentionFilter(model, GRID, belief=BeliefUpdate(0.1), forgetting=0.3)
    with pytest.raises(ValueError, match=r"\['relinearize'\], not both"):
        OnlineIntentionFilter(model, GRID, evidence=Evidence("bound"), relinearize=True)
    with pytest.raises(ValueError, match=r"\['strict'\], not both"):
        OnlineIntentionFilter(model, GRID, observations=ObservationPolicy(), strict=True)
    with pytest.raises(ValueError, match=r"\['mu0'\], not both"):
        OnlineIntentionFilter(model, GRID, state_prior=StatePrior(), mu0=torch.zeros(3))
    # a keyword left at its default says nothing
    f = OnlineIntentionFilter(model, GRID, belief=BeliefUpdate(0.1), forgetting=0.2)
    assert f.options.belief.forgetting == 0.1


def test_bad_group_values_are_refused_where_the_group_is_made():
    with pytest.raises(ValueError, match=r"forgetting \(epsilon\) must be in \[0, 1\)"):
        BeliefUpdate(forgetting=1.0)
    with pytest.raises(ValueError, match="temperature"):
        BeliefUpdate(temperature=0.0)
    with pytest.raises(ValueError, match="evidence"):
        Evidence("likelihood")
    with pytest.raises(ValueError, match="mixing='gaussian' needs"):
        Evidence("predictive", mixing="gaussian")
    assert Evidence("bound", mixing="gaussian").relinearize  # always, as documented
    with pytest.raises(ValueError, match="state_prior"):
        StatePrior("uniform")
    with pytest.raises(ValueError, match="transition"):
        TransitionPath("fast")
    with pytest.raises(TypeError, match="strict must be a bool"):
        ObservationPolicy(strict=1)
    with pytest.raises(ValueError, match="outlier_sd"):
        ObservationPolicy(outlier_sd=-1.0)


def test_a_group_of_the_wrong_type_is_refused(model):
    with pytest.raises(TypeError, match="belief must be a BeliefUpdate or None"):
        OnlineIntentionFilter(model, GRID, belief=0.2)
    with pytest.raises(TypeError, match="observations must be a ObservationPolicy or None"):
        OnlineIntentionFilter(model, GRID, observations={"strict": True})
