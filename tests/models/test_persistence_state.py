"""Model files of format 2 (issue 53, item 2): a ``state_dict`` plus a small plain configuration,
rebuilt by the registered class or loaded into a model the user's code builds (custom kernels,
priors, subclasses with object arguments), the format-1 fixtures, and the errors naming what is
missing."""

from __future__ import annotations

import io
import json
import struct
from pathlib import Path

import pytest
import torch
from gpytorch.kernels import MaternKernel, RBFKernel, ScaleKernel
from gpytorch.priors import SmoothedBoxPrior

from hgpdm_torch.models import (
    GPDM,
    HGPDM,
    IDDM,
    ModelFileError,
    load_model,
    register_model,
)
from hgpdm_torch.models.persistence import FORMAT_VERSION, MAGIC
from tests.fixtures.make_model_format1 import predictions

from .test_persistence import _loss, _pack

FIXTURES = Path(__file__).parents[1] / "fixtures"
_HEAD = struct.Struct("<IQ")
_PREFIX = len(MAGIC) + _HEAD.size + 32
CODES = [0, 1, 0, 1]
TARGETS = [0.1, -0.3, 0.7, 0.2]


def _sequences(num: int = 4, length: int = 9, dz: int = 4, seed: int = 0) -> list[torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    t = torch.linspace(0, 3, length).unsqueeze(-1)
    return [
        torch.sin(t + 0.4 * j + torch.arange(dz) * 0.7)
        + 0.05 * torch.randn(length, dz, generator=gen)
        for j in range(num)
    ]


def _unpack(path: Path) -> tuple[int, dict]:
    raw = path.read_bytes()
    version, length = _HEAD.unpack_from(raw, len(MAGIC))
    return version, torch.load(io.BytesIO(raw[_PREFIX:]), weights_only=True)


def _same_state(model: GPDM, other: GPDM) -> None:
    state, state2 = model.state_dict(), other.state_dict()
    assert list(state) == list(state2)
    for key, value in state.items():
        assert torch.equal(state2[key], value), key


def _fitted(model: GPDM) -> GPDM:
    model.fit(2, warn=False)
    return model


# ------------------------------------------------------------------------------ the format
@pytest.mark.parametrize(
    "build",
    [
        lambda s: GPDM(s, 2, learn_noise=True),
        lambda s: HGPDM(s, CODES, 2, sharing=0.3),
        lambda s: IDDM(s, TARGETS, 2, intention="continuous", phase_width=4.0),
    ],
    ids=["gpdm", "hgpdm", "iddm"],
)
def test_format2_is_state_plus_a_plain_config(tmp_path, build):
    model = _fitted(build(_sequences()))
    path = tmp_path / "m.pt"
    model.save(path)
    version, blob = _unpack(path)
    assert version == FORMAT_VERSION == blob["format"] == 2
    assert set(blob) == {"format", "class", "config", "data", "state_dict", "user_arguments"}
    assert blob["class"] == type(model).__name__ and blob["user_arguments"] == {}
    assert json.loads(json.dumps(blob["config"])) == blob["config"]  # JSON-able
    assert blob["config"] == {**model.config(), "dtype": "float64"}
    assert list(blob["state_dict"]) == list(model.state_dict())
    again = load_model(path)
    assert type(again) is type(model) and again.config() == model.config()
    _same_state(model, again)
    assert _loss(again) == _loss(model)
    g = {"GPDM": None, "HGPDM": 1, "IDDM": 0.3}[blob["class"]]
    x0 = model.latent.detach()[0]
    assert torch.equal(again.rollout(x0, 3, g), model.rollout(x0, 3, g))


# ------------------------------------------------------------------------------ custom objects
def _custom_hgpdm(seqs: list[torch.Tensor]) -> HGPDM:
    """An H-GPDM with a Matern measurement kernel and a box prior of its own."""
    return HGPDM(
        seqs,
        CODES,
        2,
        measurement=ScaleKernel(MaternKernel(nu=2.5)),
        priors={"measurement_noise": SmoothedBoxPrior(-8.0, 0.0)},
    )


def test_custom_kernel_and_prior_load_into_the_model_the_user_builds(tmp_path):
    seqs = _sequences()
    model = _fitted(_custom_hgpdm(seqs))
    path = tmp_path / "custom.pt"
    model.save(path)  # format 1 refused it
    assert _unpack(path)[1]["user_arguments"] == {"measurement": "ScaleKernel", "priors": "dict"}
    with pytest.raises(
        ModelFileError, match=r"measurement \(a ScaleKernel\), priors \(a dict\).*model=HGPDM"
    ):
        load_model(path)
    fresh = _custom_hgpdm(seqs)
    assert _loss(fresh) != _loss(model)
    again = load_model(path, model=fresh)
    assert again is fresh
    _same_state(model, again)  # latents, kernel hyperparameters, the prior's parameters
    kernel, kernel2 = model.measurement_kernel, again.measurement_kernel
    assert torch.equal(kernel2.base_kernel.lengthscale, kernel.base_kernel.lengthscale)
    assert torch.equal(kernel2.outputscale, kernel.outputscale)
    assert _loss(again) == _loss(model)
    x = torch.randn(3, 2, generator=torch.Generator().manual_seed(1))
    for got, want in zip(
        again.measurement_posterior().predict(x),
        model.measurement_posterior().predict(x),
        strict=True,
    ):
        assert torch.equal(got, want)
    assert _loss(HGPDM.load(path, model=_custom_hgpdm(seqs))) == _loss(model)


def test_a_model_built_differently_is_refused_with_the_keys(tmp_path):
    seqs = _sequences()
    path = tmp_path / "custom.pt"
    _custom_hgpdm(seqs).save(path)
    other = HGPDM(
        seqs,
        CODES,
        2,
        measurement=RBFKernel(),
        priors={"measurement_noise": SmoothedBoxPrior(-8.0, 0.0)},
    )
    with pytest.raises(ModelFileError, match="saved state does not fit the model given") as info:
        load_model(path, model=other)
    message = str(info.value)
    assert "missing from the file: ['measurement_kernel.raw_lengthscale'" in message
    assert "in the file but not in the model: [" in message
    assert "'measurement_kernel.base_kernel.raw_lengthscale'" in message
    with pytest.raises(ModelFileError, match=r"measurement_noise_prior\.tails\.loc"):
        load_model(path, model=HGPDM(seqs, CODES, 2, measurement=ScaleKernel(MaternKernel())))
    with pytest.raises(ModelFileError, match=r"other options.*sharing \(file 0\.0, model 0\.5\)"):
        load_model(path, model=HGPDM(seqs, CODES, 2, sharing=0.5))
    with pytest.raises(ModelFileError, match="holds a HGPDM, but the model given is a GPDM"):
        load_model(path, model=GPDM(seqs, 2))
    with pytest.raises(
        ModelFileError, match="torch.float64 model, the model given is torch.float32"
    ):
        load_model(path, model=HGPDM([s.float() for s in seqs], CODES, 2, dtype=torch.float32))
    with pytest.raises(TypeError, match="must be a GPDM or LinearIDDM"):
        load_model(path, model=torch.nn.Linear(2, 2))
    with pytest.raises(TypeError, match="must be a IDDM"):
        IDDM.load(path, model=HGPDM(seqs, CODES, 2))


# ------------------------------------------------------------------------------ subclasses
@register_model(name="test_persistence_state.ShrunkGPDM")
class ShrunkGPDM(GPDM):
    """Plain constructor arguments of its own, recorded without ``self._config``."""

    def __init__(self, sequences, latent_dim=3, *, shrink=0.5, offsets=(0.0, 0.0), **kwargs):
        self.shrink, self.offsets = shrink, list(offsets)
        super().__init__(sequences, latent_dim, **kwargs)

    def initial_latents(self, centred: torch.Tensor) -> torch.Tensor:
        offsets = torch.tensor(self.offsets, dtype=centred.dtype)
        return self.shrink * super().initial_latents(centred) + offsets


@register_model(name="test_persistence_state.MaternGPDM")
class MaternGPDM(GPDM):
    """Builds its custom measurement kernel itself, from a plain argument."""

    def __init__(self, sequences, latent_dim=3, *, nu=2.5, **kwargs):
        super().__init__(
            sequences, latent_dim, measurement=ScaleKernel(MaternKernel(nu=nu)), **kwargs
        )


@register_model(name="test_persistence_state.KernelIDDM")
class KernelIDDM(IDDM):
    """Takes a transition kernel object (and a plain option) of the user's."""

    def __init__(self, sequences, intentions, latent_dim=3, *, transition=None, tag="a", **kwargs):
        self._given, self.tag = [transition], tag
        super().__init__(sequences, intentions, latent_dim, **kwargs)
        del self._given

    def build_transition_kernel(self):
        given = self._given[0]
        return super().build_transition_kernel() if given is None else given


def _kernel_iddm(seqs: list[torch.Tensor], tag: str = "b") -> KernelIDDM:
    kernel = ScaleKernel(MaternKernel(nu=2.5, ard_num_dims=3))
    return KernelIDDM(seqs, TARGETS, 2, intention="continuous", transition=kernel, tag=tag)


def test_subclass_plain_arguments_round_trip(tmp_path):
    model = _fitted(ShrunkGPDM(_sequences(), 2, shrink=0.25, offsets=(1.0, -1.0), learn_noise=True))
    model.save(tmp_path / "s.pt")
    blob = _unpack(tmp_path / "s.pt")[1]
    assert blob["config"]["shrink"] == 0.25 and blob["config"]["offsets"] == (1.0, -1.0)
    again = load_model(tmp_path / "s.pt")
    assert type(again) is ShrunkGPDM and (again.shrink, again.offsets) == (0.25, [1.0, -1.0])
    assert again.learn_noise and _loss(again) == _loss(model)
    matern = _fitted(MaternGPDM(_sequences(), 2, nu=1.5))
    matern.save(tmp_path / "m.pt")
    again = load_model(tmp_path / "m.pt")  # rebuilt by the class: nothing to supply
    assert again.measurement_kernel.base_kernel.nu == 1.5
    _same_state(matern, again)
    assert _loss(again) == _loss(matern)


def test_subclass_object_argument_is_named_and_loads_into_a_user_built_model(tmp_path):
    seqs = _sequences()
    model = _fitted(_kernel_iddm(seqs))
    path = tmp_path / "k.pt"
    model.save(path)
    blob = _unpack(path)[1]
    assert blob["user_arguments"] == {"transition": "ScaleKernel"} and blob["config"]["tag"] == "b"
    with pytest.raises(
        ModelFileError, match=r"transition \(a ScaleKernel\).*KernelIDDM\(\.\.\., transition="
    ):
        load_model(path)
    again = KernelIDDM.load(path, model=_kernel_iddm(seqs))
    _same_state(model, again)
    lengthscale = again.transition_kernel.base_kernel.lengthscale
    assert torch.equal(lengthscale, model.transition_kernel.base_kernel.lengthscale)
    x0 = model.latent.detach()[0]
    assert torch.equal(again.rollout(x0, 3, 0.3), model.rollout(x0, 3, 0.3))
    with pytest.raises(ModelFileError, match=r"tag \(file 'b', model 'c'\)"):
        load_model(path, model=_kernel_iddm(seqs, tag="c"))


@register_model(name="test_persistence_state.RenamedGPDM")
class RenamedGPDM(ShrunkGPDM):
    """``shrink`` was called ``damping`` when older files were written."""

    config_renames = {"damping": "shrink"}


def test_a_renamed_keyword_still_loads(tmp_path):
    model = RenamedGPDM(_sequences(), 2, shrink=0.25)
    path = tmp_path / "r.pt"
    model.save(path)
    blob = _unpack(path)[1]
    config = {("damping" if k == "shrink" else k): v for k, v in blob["config"].items()}
    _pack(path, {**blob, "config": config})  # as the release before the rename wrote it
    again = load_model(path)
    assert again.shrink == 0.25 and _loss(again) == _loss(model)
    assert load_model(path, model=RenamedGPDM(_sequences(), 2, shrink=0.25)).shrink == 0.25


# ------------------------------------------------------------------------------ format 1
# The fixtures were written by the format-1 code (tests/fixtures/make_model_format1.py). Loading
# runs the same float64 code as the script did, but another machine's BLAS may sum in another
# order: the solves with K_x (condition number up to 2.3e5, n <= 48 rows, measured) then move
# by about n * cond * eps = 2e-9 relative, which four rollout steps may amplify a few times;
# the log posterior (about 500) moves by less than 1e-9 relative. On the machine that wrote
# them the predictions were bit-equal (checked when they were made).
RTOL, ATOL = 1e-6, 1e-9


def _format1(name: str) -> tuple[Path, dict]:
    expected = json.loads((FIXTURES / "model_format1_predictions.json").read_text())
    return FIXTURES / f"model_format1_{name}.pt", expected[name]


def _rebuilt_by_hand(name: str, model: HGPDM) -> HGPDM:
    """The fixture's model as the user's code builds it, from the same data."""
    seqs = model.sequences()
    if name == "hgpdm":
        return HGPDM(seqs, model.intention_codes(), 2, noise_per_value=True)
    options = {"phase_width": 5.0, "scale_transitions": True}
    return IDDM(seqs, model.intentions[:, 0], 2, intention="continuous", **options)


@pytest.mark.parametrize("name", ["hgpdm", "iddm"])
def test_format1_fixture_loads_and_predicts_as_saved(tmp_path, name):
    path, expected = _format1(name)
    assert path.stat().st_size < 200_000
    assert _unpack(path)[0] == 1
    model = load_model(path)
    assert type(model) is {"hgpdm": HGPDM, "iddm": IDDM}[name]
    x = torch.tensor(expected["x"], dtype=torch.float64)
    got = predictions(model, x, expected["g"])
    assert got["state_sha256"] == expected["state_sha256"]  # the saved state, bit for bit
    assert got["log_posterior"] == pytest.approx(expected["log_posterior"], rel=1e-9)
    for key in (
        "measurement_mean",
        "measurement_var",
        "rollout",
        "transition_mean",
        "transition_var",
    ):
        torch.testing.assert_close(
            torch.tensor(got[key]), torch.tensor(expected[key]), rtol=RTOL, atol=ATOL, msg=key
        )
    # the same file loaded into a model built by hand, and saved again as format 2: the same
    # code on the same machine, so bit for bit
    by_hand = load_model(path, model=_rebuilt_by_hand(name, model))
    assert predictions(by_hand, x, expected["g"]) == got
    by_hand.save(tmp_path / "v2.pt")
    assert _unpack(tmp_path / "v2.pt")[0] == 2
    assert predictions(load_model(tmp_path / "v2.pt"), x, expected["g"]) == got


# ------------------------------------------------------------------------------ errors
def test_errors_name_what_is_wrong_or_missing(tmp_path):
    seqs = _sequences()
    model = HGPDM(seqs, CODES, 2)
    path, bad = tmp_path / "m.pt", tmp_path / "bad.pt"
    model.save(path)
    _, blob = _unpack(path)
    # a wrong file
    torch.save(model.state_dict(), bad)
    with pytest.raises(ModelFileError, match="plain torch.save archive"):
        load_model(bad)
    old_layout = {
        **{k: blob[k] for k in ("class", "config", "data", "state_dict")},
        "dtype": "float64",
    }
    _pack(bad, old_layout)
    with pytest.raises(ModelFileError, match=r"missing \['format', 'user_arguments'\]"):
        load_model(bad)
    _pack(bad, {**blob, "format": 3})
    with pytest.raises(ModelFileError, match="says format 3, its header 2"):
        load_model(bad)
    _pack(bad, {**blob, "config": {**blob["config"], "shrink": torch.ones(1)}})
    with pytest.raises(ModelFileError, match="plain"):
        load_model(bad)
    # a missing or an unexpected state key
    state = {k: v for k, v in blob["state_dict"].items() if k != "raw_transition_noise"}
    _pack(bad, {**blob, "state_dict": state})
    with pytest.raises(ModelFileError, match=r"missing from the file: \['raw_transition_noise'\]"):
        load_model(bad)
    _pack(bad, {**blob, "state_dict": {**blob["state_dict"], "extra": torch.ones(1)}})
    with pytest.raises(ModelFileError, match=r"in the file but not in the model: \['extra'\]"):
        load_model(bad, model=HGPDM(seqs, CODES, 2))
    # an unknown class: registered, or built by the user's code
    _pack(bad, {**blob, "class": "nobody.Model"})
    with pytest.raises(ModelFileError, match=r"'nobody.Model', which is not registered.*model="):
        load_model(bad)
    assert _loss(load_model(bad, model=HGPDM(seqs, CODES, 2))) == _loss(model)
    # a required argument
    _pack(bad, {**blob, "user_arguments": {"measurement": "MyKernel"}})
    with pytest.raises(
        ModelFileError,
        match=r"measurement \(a MyKernel\).*model=HGPDM\(\.\.\., measurement=\.\.\.\)",
    ):
        load_model(bad)
