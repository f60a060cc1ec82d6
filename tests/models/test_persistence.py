"""Safe persistence: round trips, corruption and truncation, foreign files, the class registry,
format versions, data/state cross-checks and the noise setters' validation."""

from __future__ import annotations

import hashlib
import importlib.util
import io
import math
import struct
import sys

import numpy as np
import pytest
import torch
from gpytorch.kernels import ProductKernel

import hgpdm_torch
from hgpdm_torch.kernels import IntentionRBFKernel
from hgpdm_torch.models import (
    GPDM,
    HGPDM,
    IDDM,
    LinearIDDM,
    ModelFileError,
    load_model,
    register_model,
    registered_models,
)
from hgpdm_torch.models.gpdm import NOISE_FLOOR
from hgpdm_torch.models.persistence import FORMAT_VERSION, MAGIC

# The documented layout, re-implemented here as an independent check of the format:
# MAGIC | version <u4 | payload length <u8 | sha256(everything else) | payload.
_HEAD = struct.Struct("<IQ")
_PREFIX = len(MAGIC) + _HEAD.size + 32


def _sequences(num: int = 4, length: int = 9, dz: int = 4, seed: int = 0) -> list[torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    t = torch.linspace(0, 3, length).unsqueeze(-1)
    out = []
    for j in range(num):
        phase = 0.4 * j + torch.arange(dz) * 0.7
        out.append(torch.sin(t + phase) + 0.05 * torch.randn(length, dz, generator=gen))
    return out


def _unpack(path) -> tuple[int, dict]:
    raw = path.read_bytes()
    assert raw.startswith(MAGIC)
    version, length = _HEAD.unpack_from(raw, len(MAGIC))
    assert len(raw) == _PREFIX + length
    head, digest, payload = raw[: _PREFIX - 32], raw[_PREFIX - 32 : _PREFIX], raw[_PREFIX:]
    assert hashlib.sha256(head + payload).digest() == digest
    return version, torch.load(io.BytesIO(payload), weights_only=True)


def _pack(path, blob, version: int = FORMAT_VERSION) -> None:
    """Write ``blob`` with a valid header and checksum (a well-formed file of any content)."""
    buffer = io.BytesIO()
    torch.save(blob, buffer)
    payload = buffer.getvalue()
    head = MAGIC + _HEAD.pack(version, len(payload))
    path.write_bytes(head + hashlib.sha256(head + payload).digest() + payload)


def _loss(model: GPDM) -> float:
    with torch.no_grad():
        return float(model.loss())


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """A small fitted H-GPDM, its file, the file's bytes and its loss."""
    model = HGPDM(_sequences(), [0, 1, 0, 1], 2)
    model.fit(3, warn=False)
    path = tmp_path_factory.mktemp("saved") / "model.pt"
    model.save(path)
    return model, path, path.read_bytes(), _loss(model)


# ------------------------------------------------------------------------------ round trips
@pytest.mark.parametrize(
    "build",
    [
        lambda s: GPDM(s, 2),
        lambda s: HGPDM(s, [0, 1, 0, 1], 2),
        lambda s: HGPDM(s, [0, 1, 0, 1], 2, sharing=0.5, learn_noise=True),
        lambda s: IDDM(s, [0.1, -0.3, 0.7, 0.2], 2, intention="continuous", measurement="linear"),
        lambda s: GPDM(s, 2, back_constraint="kernel"),
    ],
    ids=["gpdm", "hgpdm", "hgpdm-sharing", "iddm-continuous", "back-constrained"],
)
def test_round_trip_rebuilds_the_same_model(tmp_path, build):
    model = build(_sequences())
    model.fit(2, warn=False)
    model.save(tmp_path / "m.pt")
    again = load_model(tmp_path / "m.pt")
    assert type(again) is type(model)
    assert again.config() == model.config()
    assert _loss(again) == _loss(model)
    state, state2 = model.state_dict(), again.state_dict()
    assert state.keys() == state2.keys()
    assert all(torch.equal(state[k], state2[k]) for k in state)
    assert again.learn_noise == model.learn_noise
    x = torch.randn(3, 2, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(
        again.measurement_posterior().predict(x),
        model.measurement_posterior().predict(x),
        rtol=0,
        atol=0,
    )
    version, blob = _unpack(tmp_path / "m.pt")
    assert version == FORMAT_VERSION
    assert blob["class"] == type(model).__name__ and blob["config"]["dtype"] == "float64"


@pytest.mark.parametrize(
    "build",
    [
        lambda s: HGPDM(s, [0.1, -0.3, 0.7, 0.2], 2, intention="continuous"),
        lambda s: IDDM(s, [0.1, -0.3, 0.7, 0.2], 2, intention="continuous", measurement="linear"),
    ],
    ids=["hgpdm-continuous", "iddm-continuous"],
)
def test_files_with_the_bespoke_intention_kernel_load_into_the_product(tmp_path, build):
    """A file saved when the continuous kinds used IntentionRBFKernel (its state dict holds
    ``raw_lengthscale_x``/``_g``) loads into today's RBF(x) * RBF(g) with the same length
    scales; the model equals the saved one to the ulp by which the two Gram matrices differ."""
    model = build(_sequences())
    model.fit(2, warn=False)
    kernel = model.transition_kernel
    scaled = kernel if isinstance(model, IDDM) else kernel.kernels[0]
    rbf_x, rbf_g = scaled.base_kernel.kernels
    old = IntentionRBFKernel(rbf_x.active_dims.numel(), rbf_g.active_dims.numel())
    old.lengthscale_x, old.lengthscale_g = rbf_x.lengthscale, rbf_g.lengthscale
    scaled.base_kernel = old
    model.save(tmp_path / "m.pt")
    assert any(k.endswith("raw_lengthscale_x") for k in _unpack(tmp_path / "m.pt")[1]["state_dict"])
    again = load_model(tmp_path / "m.pt")
    kernel = again.transition_kernel
    product = (kernel if isinstance(again, IDDM) else kernel.kernels[0]).base_kernel
    assert isinstance(product, ProductKernel)
    assert torch.equal(product.kernels[0].lengthscale, old.lengthscale_x)
    assert torch.equal(product.kernels[1].lengthscale, old.lengthscale_g)
    assert _loss(again) == pytest.approx(_loss(model), rel=1e-10)


def test_load_classmethod_checks_the_class(saved):
    model, path, _, loss = saved
    assert isinstance(GPDM.load(path), HGPDM) and _loss(HGPDM.load(path)) == loss
    with pytest.raises(ModelFileError, match="not a IDDM"):
        IDDM.load(path)


def test_error_class_is_exported():
    assert hgpdm_torch.ModelFileError is ModelFileError
    assert issubclass(ModelFileError, ValueError)
    assert {"GPDM", "HGPDM", "IDDM"} <= set(registered_models())


# ------------------------------------------------------------------------------ corruption
def test_any_200_corrupted_bytes_are_detected(saved, tmp_path):
    _, _, raw, loss = saved
    rng = np.random.default_rng(15)
    path = tmp_path / "bad.pt"
    detected = 0
    for _ in range(200):
        data = bytearray(raw)
        offset = int(rng.integers(0, len(data) - 200 + 1))
        data[offset : offset + 200] = rng.integers(0, 256, 200, dtype=np.uint8).tobytes()
        path.write_bytes(bytes(data))
        try:
            model = load_model(path)
        except ModelFileError as err:
            assert str(path) in str(err)
            detected += 1
        else:  # only acceptable if the file decodes to the very same model
            assert _loss(model) == loss
    assert detected >= 198


@pytest.mark.parametrize("keep", [1, 10, 16, 20, 27, 28, 59, 60, 61, 0.5, -1])
def test_truncated_files_are_refused(saved, tmp_path, keep):
    _, _, raw, _ = saved
    cut = int(len(raw) * keep) if isinstance(keep, float) else keep % len(raw)
    path = tmp_path / "cut.pt"
    path.write_bytes(raw[:cut])
    with pytest.raises(ModelFileError, match="truncated") as info:
        load_model(path)
    assert str(path) in str(info.value)


def test_trailing_bytes_are_refused(saved, tmp_path):
    path = tmp_path / "long.pt"
    path.write_bytes(saved[2] + b"\0")
    with pytest.raises(ModelFileError, match="longer than its header"):
        load_model(path)


def test_empty_missing_and_foreign_files(tmp_path):
    empty = tmp_path / "empty.pt"
    empty.write_bytes(b"")
    with pytest.raises(ModelFileError, match="empty"):
        load_model(empty)
    with pytest.raises(FileNotFoundError):
        load_model(tmp_path / "missing.pt")
    noise = tmp_path / "noise.pt"
    noise.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    with pytest.raises(ModelFileError, match="not an hgpdm-torch model file"):
        load_model(noise)
    plain = tmp_path / "plain.pt"
    torch.save({"a": 1}, plain)
    with pytest.raises(ModelFileError, match="plain torch.save archive"):
        load_model(plain)
    # a well-formed file whose payload is not a model
    foreign = tmp_path / "foreign.pt"
    _pack(foreign, {"a": 1})
    with pytest.raises(ModelFileError, match="payload must be a dict"):
        load_model(foreign)


# ------------------------------------------------------------------------------ versions
def test_unknown_format_versions_are_refused(saved, tmp_path):
    raw = bytearray(saved[2])
    path = tmp_path / "v.pt"
    for version, match in ((FORMAT_VERSION + 1, "newer"), (2**32 - 1, "newer"), (0, "unknown")):
        raw[len(MAGIC) : len(MAGIC) + 4] = struct.pack("<I", version)
        path.write_bytes(bytes(raw))
        with pytest.raises(ModelFileError, match=match) as info:
            load_model(path)
        assert f"version {version}" in str(info.value)


# ------------------------------------------------------------------------------ registry
def test_class_names_are_looked_up_never_imported(saved, tmp_path, monkeypatch):
    marker = tmp_path / "imported.txt"
    (tmp_path / "hgpdm_probe_side_effect.py").write_text(
        f"import pathlib\npathlib.Path({str(marker)!r}).write_text('imported')\n"
        "class Foo:\n    pass\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    assert importlib.util.find_spec("hgpdm_probe_side_effect") is not None  # importable
    _, blob = _unpack(saved[1])
    path = tmp_path / "named.pt"
    for name in (
        "os:system",
        "somemodule:Foo",
        "hgpdm_probe_side_effect:Foo",
        "hgpdm_probe_side_effect.Foo",
        "hgpdm_torch.models.hgpdm:HGPDM",  # the old format's name: no longer resolved
    ):
        _pack(path, {**blob, "class": name})
        with pytest.raises(ModelFileError, match="register_model") as info:
            load_model(path)
        assert repr(name) in str(info.value)
    assert not marker.exists()
    assert "hgpdm_probe_side_effect" not in sys.modules


@register_model(name="test_persistence.DampedGPDM")
class DampedGPDM(GPDM):
    """A user's subclass with an extra constructor option, kept in its configuration."""

    def __init__(self, sequences, latent_dim: int = 3, *, damping: float = 0.5, **kwargs):
        self.damping = float(damping)
        super().__init__(sequences, latent_dim, **kwargs)
        self._config["damping"] = self.damping

    def initial_latents(self, centred: torch.Tensor) -> torch.Tensor:
        return self.damping * super().initial_latents(centred)


def test_user_registered_subclass_round_trip(tmp_path):
    assert registered_models()["test_persistence.DampedGPDM"] is DampedGPDM
    model = DampedGPDM(_sequences(), 2, damping=0.25)
    model.fit(2, warn=False)
    model.save(tmp_path / "d.pt")
    assert _unpack(tmp_path / "d.pt")[1]["class"] == "test_persistence.DampedGPDM"
    again = load_model(tmp_path / "d.pt")
    assert type(again) is DampedGPDM and again.damping == 0.25
    assert _loss(again) == _loss(model)


def test_unregistered_subclasses_and_name_clashes(tmp_path):
    class Unregistered(GPDM):
        pass

    with pytest.raises(TypeError, match="register_model"):
        Unregistered(_sequences(), 2).save(tmp_path / "u.pt")
    assert not list(tmp_path.iterdir())  # nothing, not even a temporary file, is left behind
    with pytest.raises(ValueError, match="already registered"):
        register_model(Unregistered, name="GPDM")
    with pytest.raises(ValueError, match="already registered as"):
        register_model(GPDM, name="another name")
    with pytest.raises(TypeError, match="subclass of GPDM"):
        register_model(torch.nn.Linear)
    assert register_model(GPDM) is GPDM  # registering again under its own name is harmless


@register_model(name="test_persistence.ForgetfulGPDM")
class ForgetfulGPDM(GPDM):
    """A subclass whose extra constructor option is not in its configuration."""

    def __init__(self, sequences, latent_dim: int = 3, *, extra: int = 5, **kwargs):
        super().__init__(sequences, latent_dim, **kwargs)
        self.extra = extra


@register_model(name="test_persistence.FixedSignatureGPDM")
class FixedSignatureGPDM(GPDM):
    """A subclass whose constructor does not take the saved options back."""

    def __init__(self, sequences, latent_dim: int = 3, dtype: torch.dtype = torch.float64):
        super().__init__(sequences, latent_dim, dtype=dtype)


def test_subclass_arguments_are_saved_without_being_added_to_the_config(tmp_path):
    """Issue 54: a subclass built with extra=9 saved, and loaded with extra=5. Its constructor's
    own plain arguments are now recorded and saved (format 2), without ``self._config``; a
    subclass whose constructor refuses the saved options is saved, and loading it names the
    cause and the way out (building it in code: ``model=``)."""
    ForgetfulGPDM(_sequences(), 2, extra=9).save(tmp_path / "f.pt")
    assert _unpack(tmp_path / "f.pt")[1]["config"]["extra"] == 9
    assert load_model(tmp_path / "f.pt").extra == 9
    model = FixedSignatureGPDM(_sequences(), 2)
    model.save(tmp_path / "g.pt")
    with pytest.raises(ModelFileError, match=r"do not rebuild.*unexpected keyword.*model=") as info:
        load_model(tmp_path / "g.pt")
    assert str(tmp_path / "g.pt") in str(info.value)
    again = load_model(tmp_path / "g.pt", model=FixedSignatureGPDM(_sequences(), 2))
    assert _loss(again) == _loss(model)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.pt", "g.pt"]


def test_save_names_a_missing_folder(tmp_path):
    """Issue 54: saving into a missing folder named a hidden temporary file."""
    model = GPDM(_sequences(), 2)
    with pytest.raises(FileNotFoundError, match="the folder .*nowhere.* does not exist") as err:
        model.save(tmp_path / "nowhere" / "m.pt")
    assert ".tmp" not in str(err.value)
    (tmp_path / "file").write_text("")
    with pytest.raises(NotADirectoryError, match="is a file, not a folder"):
        model.save(tmp_path / "file" / "m.pt")
    (tmp_path / "dir.pt").mkdir()
    with pytest.raises(IsADirectoryError, match="it is a folder"):
        model.save(tmp_path / "dir.pt")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir.pt", "file"]


# ------------------------------------------------------------------------------ consistency
def test_training_data_and_saved_state_must_agree(saved, tmp_path):
    _, blob = _unpack(saved[1])
    path = tmp_path / "mismatch.pt"
    state = dict(blob["state_dict"])
    state["observations"] = state["observations"].clone()
    state["observations"][3, 1] += 1e-3
    data = {**blob["data"], "intentions": 1 - blob["data"]["intentions"]}
    sequences = [s.clone() for s in blob["data"]["sequences"]]
    sequences[0][0, 0] += 1.0
    for bad in (
        {**blob, "state_dict": state},
        {**blob, "data": data},
        {**blob, "data": {**blob["data"], "sequences": sequences}},
    ):
        _pack(path, bad)
        with pytest.raises(ModelFileError, match="training data"):
            load_model(path)
    _pack(path, {**blob, "config": {**blob["config"], "dtype": "Tensor"}})
    with pytest.raises(ModelFileError, match="dtype"):
        load_model(path)
    _pack(path, {**blob, "config": {**blob["config"], "latent_dim": 3}})
    with pytest.raises(ModelFileError, match="saved state does not fit"):
        load_model(path)
    _pack(path, {**blob, "config": {**blob["config"], "unknown_option": 1}})
    with pytest.raises(ModelFileError, match="do not rebuild"):
        load_model(path)
    _pack(path, blob)  # the unmodified content loads
    assert _loss(load_model(path)) == saved[3]


# ------------------------------------------------------------------------------ noise setters
@pytest.mark.parametrize("attribute", ["measurement_noise", "transition_noise"])
@pytest.mark.parametrize(
    "value", [0.0, -0.1, math.nan, math.inf, -math.inf, 0.5 * NOISE_FLOOR, torch.tensor(0.0)]
)
def test_noise_setters_refuse_values_outside_the_range(attribute, value):
    model = GPDM(_sequences(2), 2)
    before = getattr(model, attribute).clone()
    with pytest.raises(ValueError, match=f"{attribute} must be finite") as info:
        setattr(model, attribute, value)
    message = str(info.value)
    assert "(1e-06, inf)" in message and repr(float(value)) in message
    assert torch.equal(getattr(model, attribute), before)  # unchanged


def test_noise_setters_accept_floats_and_0_dim_tensors():
    model = GPDM(_sequences(2), 2)
    model.measurement_noise = 0.02
    model.transition_noise = torch.tensor(0.003)
    assert float(model.measurement_noise.detach()) == pytest.approx(0.02, rel=1e-12)
    assert float(model.transition_noise.detach()) == pytest.approx(0.003, rel=1e-6)
    bound = float(model.raw_measurement_noise_constraint.lower_bound)
    with pytest.raises(ValueError, match="measurement_noise"):
        model.measurement_noise = bound  # exactly at the bound: raw would be -inf
    with pytest.raises(ValueError, match="scalar or broadcast"):
        model.transition_noise = torch.ones(3)
    with pytest.raises(TypeError, match="real number"):
        model.transition_noise = "0.1"
    assert math.isfinite(_loss(model))


# ------------------------------------------------------------------------------ LinearIDDM
def _saved_linear(tmp_path, name: str = "linear.pt"):
    """A LinearIDDM fitted on ``_linear_data``, its file and the file's payload."""
    obs, g = _linear_data(False)
    model = LinearIDDM().fit(obs, g)
    path = tmp_path / name
    model.save(path)
    return model, obs, g, path, _unpack(path)[1]


def _linear_data(discrete: bool, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    g = torch.randint(0, 3, (24,), generator=gen) if discrete else torch.rand(24, generator=gen)
    obs = torch.randn(24, 5, 3, generator=gen).cumsum(1) + 0.5 * g[:, None, None]
    return obs, g


@pytest.mark.filterwarnings("ignore:LinearIDDM")
@pytest.mark.parametrize(
    "options",
    [
        {},
        {"temperature": "cv", "forgetting": "cv"},
        {"intention": "discrete", "phase": False},
        {"dtype": torch.float32},
        {"interaction_rank": 1, "temperature": "cv", "forgetting": "cv"},
        {"intention": "discrete", "interaction_rank": 2},
        {"select": "cv", "temperature": "cv", "forgetting": "cv"},
    ],
    ids=["default", "calibrated", "discrete-shared", "float32", "interaction", "r2", "selected"],
)
def test_linear_iddm_round_trip(tmp_path, options):
    obs, g = _linear_data(options.get("intention") == "discrete")
    model = LinearIDDM(**options).fit(list(obs[:20]), g[:20])
    path = tmp_path / "linear.pt"
    model.save(path)
    loaded = load_model(path)
    assert type(loaded) is LinearIDDM and isinstance(LinearIDDM.load(path), LinearIDDM)
    assert loaded.config() == model.config()
    for key, value in model.state_dict().items():  # the saved statistics, bit for bit
        assert torch.equal(loaded.state_dict()[key], value)
    assert loaded.log_marginal_likelihood() == model.log_marginal_likelihood()
    assert torch.equal(loaded.beliefs(obs[20:]).prob, model.beliefs(obs[20:]).prob)
    with pytest.raises(ModelFileError, match="not a IDDM"):
        IDDM.load(path)
    assert registered_models()["LinearIDDM"] is LinearIDDM


@pytest.mark.filterwarnings("ignore:LinearIDDM")
def test_linear_iddm_statistics_must_come_from_its_data(tmp_path):
    model, obs, g, path, blob = _saved_linear(tmp_path)
    assert set(blob["config"]) >= {"noise", "coef_precision", "temperature", "forgetting"}
    assert "auto" not in blob["config"].values()  # the choices, so no search on loading
    coef = blob["state_dict"]["coef"].clone()
    coef[0, 0, 0] += 1e-3
    _pack(path, {**blob, "state_dict": {**blob["state_dict"], "coef": coef}})
    with pytest.raises(ModelFileError, match="belong to other data"):
        load_model(path)
    _pack(path, {**blob, "state_dict": {**blob["state_dict"], "coef": coef[:, :2]}})
    with pytest.raises(ModelFileError, match="do not fit the data"):
        load_model(path)
    scatter = blob["state_dict"]["scatter"][:, :2]
    _pack(path, {**blob, "state_dict": {**blob["state_dict"], "scatter": scatter}})
    with pytest.raises(ModelFileError, match="saved state does not fit"):
        load_model(path)
    _pack(path, {**blob, "data": {**blob["data"], "intentions": g[:5]}})
    with pytest.raises(ModelFileError, match="do not rebuild"):
        load_model(path)
    with pytest.raises(RuntimeError, match="not fitted"):
        LinearIDDM().save(tmp_path / "unfitted.pt")
    # a file may not ask for a search, nor for statistics its data do not imply (checked
    # before any fitting, so a small file cannot ask for a large fit)
    _pack(path, {**blob, "config": {**blob["config"], "noise": "auto"}})
    with pytest.raises(ModelFileError, match="asks for a search"):
        load_model(path)
    discrete = LinearIDDM(intention="discrete").fit(obs, (g * 3).long().clamp(max=2))
    discrete.save(path)
    _, blob = _unpack(path)
    _pack(path, {**blob, "config": {**blob["config"], "num_values": 10**7}})
    with pytest.raises(ModelFileError, match="do not fit the data"):
        load_model(path)


@pytest.mark.filterwarnings("ignore:LinearIDDM")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_linear_iddm_loads_statistics_of_another_summation_order(tmp_path, dtype):
    # another machine's BLAS sums in another order: the same model fitted on the sequences in
    # reverse order (same statistics up to rounding) is accepted; its file's data are the
    # forward ones, so loading refits them and compares
    obs, g = _linear_data(False, seed=3)
    obs[..., 2] = obs[..., 1] + 1e-3 * obs[..., 0]  # two nearly collinear features
    forward = LinearIDDM(dtype=dtype).fit(obs, g)
    backward = LinearIDDM(**forward.config(), dtype=dtype).fit(obs.flip(0), g.flip(0))
    path = tmp_path / "linear.pt"
    forward.save(path)
    _, blob = _unpack(path)
    state = backward.state_dict()
    state["intentions"] = forward.state_dict()["intentions"]  # the order of the intentions
    _pack(path, {**blob, "state_dict": state})
    assert torch.equal(load_model(path).coef, backward.coef)


@pytest.mark.filterwarnings("ignore:LinearIDDM")
def test_linear_iddm_files_from_before_the_interaction_option_load(tmp_path):
    model, obs, _, path, blob = _saved_linear(tmp_path, "old.pt")
    config = {k: v for k, v in blob["config"].items() if k != "interaction_rank"}
    state = {k: v for k, v in blob["state_dict"].items() if k != "directions"}
    _pack(path, {**blob, "config": config, "state_dict": state})
    assert torch.equal(load_model(path).beliefs(obs).prob, model.beliefs(obs).prob)


def test_linear_iddm_keeps_its_own_copy_of_the_data(tmp_path):
    obs, g = _linear_data(False)
    obs, g = obs.double(), g.double()
    model = LinearIDDM().fit(obs, g)
    obs += 1.0  # the caller changes its arrays after fitting
    g += 1.0
    model.save(tmp_path / "linear.pt")
    assert torch.equal(load_model(tmp_path / "linear.pt").coef, model.coef)
