"""The `hgpdm` command and the style-discovery experiment."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

import hgpdm_torch
from hgpdm_torch import cli
from hgpdm_torch.datasets import styled_movements
from hgpdm_torch.experiments.arguments import MAX_SEED
from hgpdm_torch.experiments.style_discovery import run_style_discovery, style_purity
from hgpdm_torch.models import HGPDM

HEAVY = ("torch", "gpytorch", "pyro", "sapien", "numpy", "scipy", "sklearn", "matplotlib")


@pytest.mark.filterwarnings("ignore::hgpdm_torch.fitting.ConvergenceWarning")  # smoke-size fits
def test_style_discovery_runs_and_discovers_styles(tmp_path, capsys):
    assert cli.main(["style-discovery", "--quick", "--out", str(tmp_path)]) == 0
    table = json.loads((tmp_path / "style_discovery.json").read_text())
    discovered = [r for r in table["rows"] if r["styles"] == "discovered (Alg. 2.1)"][0]
    assert discovered["style purity"] >= 0.9 and discovered["adjusted Rand index"] >= 0.7
    kmeans = [r for r in table["rows"] if r["model"].startswith("k-means")][0]
    assert 0 < kmeans["style purity"] <= 1 and -1 <= kmeans["adjusted Rand index"] <= 1
    assert (tmp_path / "latent_trajectories.png").stat().st_size > 10_000
    assert "style purity" in capsys.readouterr().out


def test_style_discovery_on_weird_walking_needs_the_cmu_folder(tmp_path, capsys):
    with pytest.raises(SystemExit):
        cli.main(["style-discovery", "--data", "weird-walking", "--cmu", str(tmp_path / "no")])
    assert "--cmu" in capsys.readouterr().err
    with pytest.raises(ValueError, match="data must be"):
        run_style_discovery(data="dancers")


def test_help_and_unknown_command(capsys):
    assert cli.main([]) == 0
    assert "demo" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        cli.main(["no-such-command"])


def test_help_imports_no_heavy_package():
    """``hgpdm --help`` runs the console script's code (``hgpdm_torch.cli:main``) without
    loading torch & co.: the package's exports are lazy (PEP 562)."""
    code = (
        "import sys\n"
        "from hgpdm_torch.cli import main\n"
        "sys.argv = ['hgpdm', '--help']\n"
        "rc = main()\n"
        f"print('HEAVY', sorted(m for m in {HEAVY!r} if m in sys.modules))\n"
        "raise SystemExit(rc)\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    assert "style-discovery" in run.stdout and "usage: hgpdm" in run.stdout
    assert "HEAVY []" in run.stdout
    # and as a module, the way ``python -m hgpdm_torch.cli`` is documented
    run = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "hgpdm_torch.cli", "--help"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 0 and "walkers" in run.stdout
    imported = {line.split("|")[-1].strip() for line in run.stderr.splitlines()}
    assert not imported & set(HEAVY), sorted(imported & set(HEAVY))


def test_every_public_name_resolves():
    assert hgpdm_torch.__all__ == sorted(hgpdm_torch.__all__)
    assert {"HGPDM", "IDDM", "GPDM", "load_model", "ModelFileError"} <= set(hgpdm_torch.__all__)
    for name in hgpdm_torch.__all__:
        value = getattr(hgpdm_torch, name)
        assert value is not None
        namespace: dict = {}
        exec(f"from hgpdm_torch import {name} as x", namespace)
        assert namespace["x"] is value
    assert set(hgpdm_torch.__all__) <= set(dir(hgpdm_torch))
    assert hgpdm_torch.HGPDM is HGPDM and hgpdm_torch.models.HGPDM is HGPDM
    assert issubclass(hgpdm_torch.ModelFileError, ValueError)
    with pytest.raises(AttributeError, match="no_such_name"):
        hgpdm_torch.no_such_name  # noqa: B018


@pytest.fixture
def a_file(tmp_path):
    path = tmp_path / "a_file.txt"
    path.write_text("x")
    return path


SEED_RANGE = f"expected a seed in [0, {MAX_SEED}]"
UNWRITABLE = "/proc/hgpdm_no"

# (command and arguments, fragment of the message); "{file}"/"{dir}" are an existing file/folder
BAD_ARGUMENTS = [
    (["style-discovery", "--seed", "-1"], f"argument --seed: {SEED_RANGE}, got -1"),
    (["style-discovery", "--seed", "1.5"], f"argument --seed: {SEED_RANGE}, got '1.5'"),
    (["style-discovery", "--seed", str(MAX_SEED + 1)], "argument --seed"),
    (["style-discovery", "--out", "{file}"], "argument --out: {file} is a file, expected a folder"),
    (["style-discovery", "--out", "{file}/sub"], "argument --out: {file}/sub: {file} is a file"),
    (["style-recognition", "--lengths", "0"], "argument --lengths: expected a positive integer"),
    (["style-recognition", "--lengths", "5", "-2"], "argument --lengths: expected a positive"),
    (["style-recognition", "--lengths", "5", "40"], "argument --lengths: windows must be shorter"),
    (["style-recognition", "--fit-steps", "0"], "argument --fit-steps: expected a positive"),
    (["style-recognition", "--seed", "-1"], "argument --seed"),
    (["style-recognition", "--out", "{dir}"], "argument --out: {dir} is a folder"),
    (["style-recognition", "--figure", "{dir}"], "argument --figure: {dir} is a folder"),
    (["style-recognition", "--data", "mocap"], "argument --data: invalid choice: 'mocap'"),
    (["anticipation", "--trials", "0"], "argument --trials: expected a positive integer"),
    (["anticipation", "--folds", "1"], "argument --folds: expected an integer >= 2, got 1"),
    (["anticipation", "--folds", "30"], "folds must be in [2, num_trials=24], got 30"),
    (["anticipation", "--repetitions", "0"], "argument --repetitions: expected a positive"),
    (["anticipation", "--workers", "-1"], "argument --workers: expected a positive integer"),
    (["anticipation", "--seed", "x"], "argument --seed"),
    (["anticipation", "--out", "{file}"], "argument --out: {file} is a file"),
    (["anticipation", "--cache-dir", "{file}"], "argument --cache-dir: {file} is a file"),
    (["target-prediction", "--seed", "-1"], "argument --seed"),
    (["target-prediction", "--out", "{dir}"], "argument --out: {dir} is a folder"),
    (["target-prediction", "--init", "ica"], "argument --init: invalid choice"),
    (["games", "stationary", "--seed", "-7"], "argument --seed"),
    (["games", "switch", "--json", "{dir}"], "argument --json: {dir} is a folder"),
    (["games", "poker"], "argument experiment: invalid choice"),
    (["demo", "--trials", "0"], "argument --trials: expected a positive integer"),
    (["demo", "--watched", "-1"], "argument --watched: expected an integer >= 10"),
    (["demo", "--workers", "0"], "argument --workers: expected a positive integer"),
    (["demo", "--seed", "-1"], "argument --seed"),
    (["demo", "--out", "{file}"], "argument --out: {file} is a file"),
    (["demo", "--cache-dir", "{file}"], "argument --cache-dir: {file} is a file"),
    (["demo", "--full", "--trials", "3"], "--full uses the thesis's"),
    (["anticipation", "--ray-address", "head"], "argument --ray-address"),
    (["demo", "--ray-address", "a:b:c"], "argument --ray-address"),
    (["walkers", "--sharing", "1.5"], "--sharing must lie in [0, 1)"),
    # a path the process cannot write (a virtual file system refuses even root): refused before
    # the work, not after it
    (["demo", "--out", UNWRITABLE], f"argument --out: {UNWRITABLE} cannot be written"),
    (["demo", "--cache-dir", UNWRITABLE], f"argument --cache-dir: {UNWRITABLE} cannot be"),
    (["anticipation", "--out", UNWRITABLE + "/sub"], "argument --out: /proc/hgpdm_no/sub cannot"),
    (["games", "switch", "--json", UNWRITABLE], "argument --json: /proc/hgpdm_no cannot be"),
    (["target-prediction", "--out", UNWRITABLE], "argument --out: /proc/hgpdm_no cannot be"),
    (["walkers", "--out", UNWRITABLE], "argument --out: /proc/hgpdm_no cannot be written"),
    (["action-recognition", "--dataset", "kinect"], "argument --dataset: invalid choice"),
]


@pytest.mark.parametrize(
    "argv,fragment", BAD_ARGUMENTS, ids=[" ".join(a) for a, _ in BAD_ARGUMENTS]
)
def test_bad_values_end_in_usage_messages(argv, fragment, tmp_path, a_file, capsys, monkeypatch):
    """Every bad value is an argparse error (exit 2, usage, the option named), raised before
    any data is made or model fitted: the work functions are replaced by ones that fail."""
    from hgpdm_torch.experiments import (
        anticipation,
        demo,
        repeated_games,
        style_discovery,
        style_recognition,
        target_prediction,
    )

    def no_work(*args, **kwargs):
        raise AssertionError("the work started despite a bad argument")

    for module, name in [
        (style_discovery, "run_style_discovery"),
        (style_recognition, "style_recognition"),
        (anticipation, "run_experiment"),
        (target_prediction, "target_prediction"),
        (repeated_games, "stationary_rps"),
        (repeated_games, "switching_rps"),
        (demo, "run_demo"),
    ]:
        monkeypatch.setattr(module, name, no_work)
    monkeypatch.setenv("HGPDM_SMOKE", "0")
    fill = {"{file}": str(a_file), "{dir}": str(tmp_path)}
    for key, value in fill.items():
        argv = [a.replace(key, value) for a in argv]
        fragment = fragment.replace(key, value)
    with pytest.raises(SystemExit) as exit_info:
        cli.main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: hgpdm " + argv[0]), err
    assert fragment in err, err


def test_good_values_reach_the_work(tmp_path, monkeypatch, capsys):
    from hgpdm_torch.experiments import style_discovery

    got = {}

    def fake(**kwargs):
        got.update(kwargs)
        raise SystemExit(0)

    monkeypatch.setattr(style_discovery, "run_style_discovery", fake)
    with pytest.raises(SystemExit):
        cli.main(["style-discovery", "--seed", str(MAX_SEED), "--out", str(tmp_path / "new")])
    assert got["seed"] == MAX_SEED


def test_style_purity():
    truth = torch.tensor([0, 0, 1, 1, 2, 2])
    assert style_purity(truth, torch.tensor([2, 2, 0, 0, 1, 1])) == 1.0
    assert style_purity(truth, torch.tensor([0, 0, 0, 0, 0, 0])) == pytest.approx(2 / 6)
    with pytest.raises(ValueError, match="truth"):
        style_purity(truth, torch.tensor([0, 1]))


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"seed": -1}, "seed must be a non-negative int, got -1"),
        ({"seed": 1.5}, "seed must be a non-negative int"),
        ({"seed": True}, "seed must be a non-negative int"),
        ({"iterations": 0}, "iterations must be a positive int, got 0"),
        ({"iterations": 2.0}, "iterations must be a positive int"),
        ({"steps": 0}, "steps must be a positive int, got 0"),
        ({"steps": -5}, "steps must be a positive int"),
        ({"num_styles": 0}, "num_styles must be a positive int"),
    ],
)
def test_discover_validates_its_arguments_first(kwargs, match):
    data = styled_movements(2, 2, 10, 4, seed=0)
    args = {"num_styles": 2, "iterations": 1, "steps": 1, **kwargs}
    with pytest.raises(ValueError, match=match):
        HGPDM.discover(data.sequences, args.pop("num_styles"), args.pop("iterations"), **args)


def test_discover_takes_numpy_integers():
    data = styled_movements(2, 2, 10, 4, seed=0)
    model = HGPDM.discover(data.sequences, 2, np.int64(1), steps=np.int32(2), seed=np.uint32(3))
    assert model.intention_codes().shape == (4,)
