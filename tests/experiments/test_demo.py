"""``hgpdm demo``: the anticipatory player end to end on a few strokes simulated in SAPIEN."""

from __future__ import annotations

import contextlib
import io
import json
import sys
import warnings

import pytest
import torch

pytest.importorskip("sapien")

from hgpdm_torch import cli  # noqa: E402
from hgpdm_torch.experiments import demo, intervals  # noqa: E402
from hgpdm_torch.experiments.demo import run_demo  # noqa: E402

STAGES = ("simulate:", "fit:", "learn:", "play:")


@pytest.fixture(scope="module")
def played(tmp_path_factory):
    """One small CLI run (16 strokes, 20 watched, 1 process): its output folder, stdout, stderr
    and the :class:`~hgpdm_torch.experiments.demo.DemoResult` it printed; the warnings it
    raised are in ``played_warnings``."""
    tmp = tmp_path_factory.mktemp("demo")
    out = tmp / "out"
    results = []
    real = demo.run_demo

    def spy(**kwargs):
        results.append(real(**kwargs))
        return results[-1]

    args = ["demo", "--trials", "16", "--watched", "20", "--workers", "1", "--out", str(out)]
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(demo, "run_demo", spy)
        stdout, stderr = io.StringIO(), io.StringIO()
        with (
            contextlib.redirect_stdout(stdout),
            contextlib.redirect_stderr(stderr),
            warnings.catch_warnings(record=True) as caught,
        ):
            warnings.simplefilter("always")
            assert cli.main([*args, "--cache-dir", str(tmp / "cache")]) == 0
    PLAYED_WARNINGS[:] = caught
    return out, stdout.getvalue(), stderr.getvalue(), results[0]


PLAYED_WARNINGS: list[warnings.WarningMessage] = []


def test_the_main_job_warns_of_nothing_and_reports_its_fit(played):
    """No warning a user cannot act on (a fit at its step budget, SAPIEN's missing Vulkan): the
    GP IDDM's FitResult and the LinearIDDMs' chosen settings are in the result instead."""
    out, _, stderr, _ = played
    assert [str(w.message) for w in PLAYED_WARNINGS] == []
    assert "Warning" not in stderr
    fits = json.loads((out / "demo.json").read_text())["meta"]["belief fits"]
    assert sorted(fits) == ["gp-iddm", "linear-iddm", "promp"]  # the candidates of auto
    (gp,) = fits["gp-iddm"]  # the one GP IDDM of the watched strokes
    assert gp["steps"] >= 1 and isinstance(gp["converged"], bool) and gp["reason"]
    assert [f["interaction_rank"] for f in fits["linear-iddm"]] == [0, 1]
    (promp,) = fits["promp"]  # the ProMP's options, chosen by cross-validation
    assert set(promp["options"]) == {"num_basis", "speeds", "reg"}


def test_demo_plays_rallies_in_sapien(played):
    out, stdout, stderr, result = played
    table = json.loads((out / "demo.json").read_text())
    players = [r["player"] for r in table["rows"]]
    assert players == [
        demo.BLIND, demo.FIXED_TIME, "LSPI", "MCP", "LSPI (linear-iddm belief)",
        "LSPI (gp-iddm belief)", "LSPI (promp belief)", "MCP (oracle belief)",
        "oracle (best movement and time per stroke)", "best blind (after the fact)",
    ]  # fmt: skip
    assert table["columns"] == ["player", "returns", "rate", "95% low", "95% high", "played in"]
    n_test = table["meta"]["valid"]
    # cross-fitting: every stroke inside the hitting region is a test rally once
    assert len(result.rallies) == n_test == len({r.trial for r in result.rallies}) >= 9
    assert f"{n_test} test rallies" in table["title"]
    for row in table["rows"]:
        assert 0 <= row["returns"] <= n_test
        assert row["rate"] == pytest.approx(row["returns"] / n_test)
        low, high = intervals.return_rate_interval(row["returns"], n_test)
        assert (row["95% low"], row["95% high"]) == pytest.approx((low, high))
        assert row["95% low"] <= row["rate"] <= row["95% high"]
    returns = {r["player"]: r["returns"] for r in table["rows"]}
    # the oracle knows each stroke's best movement and time: every kept stroke is returnable
    assert returns["oracle (best movement and time per stroke)"] == n_test
    # no strategy chosen on the training folds beats the one chosen on the test rallies
    assert returns[demo.BLIND] <= returns["best blind (after the fact)"]
    # the paired differences: MCP and LSPI against both baselines on the same rallies
    meta = table["meta"]
    assert meta["belief used"] in ("linear-iddm", "gp-iddm") or meta["belief used"].startswith(
        "per fold: "
    )
    assert meta[demo.BLIND].startswith(("always ", "per fold: "))
    assert "@" in meta[demo.FIXED_TIME]
    for player in ("MCP", "LSPI"):
        for other in (demo.BLIND, demo.FIXED_TIME):
            key = f"{player} - {other}"
            expected = intervals.paired_difference_interval(
                result.successes[player], result.successes[other]
            )
            got = (meta[key], meta[f"{key} 95% low"], meta[f"{key} 95% high"])
            assert got == pytest.approx(expected)
            assert meta[key] == pytest.approx((returns[player] - returns[other]) / n_test)
            assert key in stdout
    assert meta["verdict"] in stdout
    # the rally figure's belief is the one the players used for that rally's fold
    assert result.target_probs.shape == (n_test, 5, 25)
    for j, source in enumerate(result.sources):
        assert torch.equal(result.target_probs[j], result.beliefs[source][j])
    # the live SAPIEN rallies reproduce the reward table of the deterministic scene
    assert meta["live = table"] == f"{n_test}/{n_test}"
    for name in ("return_rates.png", "rally.png"):
        assert (out / name).stat().st_size > 10_000
    assert "| MCP |" in stdout
    # not a terminal: no bars, one status line per stage on stderr, the results on stdout
    status = [line for line in stderr.splitlines() if line.startswith("[hgpdm demo")]
    for stage in STAGES:
        assert sum(stage in line for line in status) == 1, (stage, status)
    assert "reward table:" not in stderr and "|" not in stderr


@pytest.mark.parametrize(
    "flags,tty,bars,lines",
    [
        ([], False, False, True),
        ([], True, True, True),
        (["--progress"], False, True, True),
        (["--quiet"], True, False, False),
        (["--quiet"], False, False, False),
    ],
)
def test_progress_follows_the_terminal_and_the_flags(
    played, flags, tty, bars, lines, tmp_path, monkeypatch, capsys
):
    """Bars on a terminal (or with --progress), status lines unless --quiet; the work itself is
    the module run's result, replayed."""
    result = played[3]
    seen = {}

    def replay(**kwargs):
        seen.update(kwargs)
        if kwargs["status"] is not None:
            for stage in STAGES:
                kwargs["status"](f"{stage} replayed")
        return result

    monkeypatch.setattr(demo, "run_demo", replay)
    monkeypatch.setattr(demo, "plot_demo", lambda result, out: [])
    monkeypatch.setattr(sys.stderr, "isatty", lambda: tty)
    assert cli.main(["demo", "--out", str(tmp_path), *flags]) == 0
    assert seen["progress"] is bars and (seen["status"] is not None) is lines
    out, err = capsys.readouterr()
    assert "| MCP |" in out and f"MCP - {demo.FIXED_TIME}" in out
    status = [line for line in err.splitlines() if line.startswith("[hgpdm demo")]
    assert len(status) == (len(STAGES) + 1 if lines else 0), err
    if not lines:
        assert err == ""


def test_demo_rejects_bad_arguments(capsys):
    with pytest.raises(ValueError, match="folds"):
        run_demo(folds=1)
    with pytest.raises(ValueError, match="watched"):
        run_demo(watched=-1)
    with pytest.raises(ValueError, match="num_trials"):
        run_demo(num_trials=0)
    with pytest.raises(ValueError, match="workers"):
        run_demo(workers=-2)
    with pytest.raises(TypeError, match="status"):
        run_demo(status="loud")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="unknown belief .oracle."):
        run_demo(belief="oracle")  # a reference row, never the players' belief
    with pytest.raises(ValueError, match="features"):
        run_demo(features="histogram")
    with pytest.raises(ValueError, match="wait_value"):
        run_demo(wait_value="forever")
    for argv, fragment in [
        (["--folds", "1"], "argument --folds: expected an integer >= 2"),
        (["--quiet", "--progress"], "argument --progress: not allowed with argument --quiet"),
        (["--trials", "many"], "argument --trials: expected a positive integer"),
        (["--belief", "psychic"], "argument --belief: invalid choice: 'psychic'"),
        (["--belief", "oracle"], "argument --belief: invalid choice: 'oracle'"),
        (["--features", "pixels"], "argument --features: invalid choice: 'pixels'"),
        (["--wait-value", "forever"], "argument --wait-value: invalid choice: 'forever'"),
    ]:
        with pytest.raises(SystemExit) as exit_info:
            cli.main(["demo", *argv])
        assert exit_info.value.code == 2
        assert fragment in capsys.readouterr().err


def test_demo_full_forwards_the_belief_features_and_wait_value(monkeypatch, tmp_path):
    """``hgpdm demo --full`` runs the full protocol with the demo's --belief, --features and
    --wait-value."""
    seen = []
    monkeypatch.setattr(demo.ant, "main", lambda argv: seen.append(argv) or 0)
    args = ["demo", "--full", "--belief", "gp-iddm", "--features", "rbf", "--wait-value", "stop",
            "--out", str(tmp_path)]  # fmt: skip
    assert cli.main(args) == 0
    (argv,) = seen
    assert argv[0] == "--full"
    assert argv[argv.index("--belief") + 1] == "gp-iddm"
    assert argv[argv.index("--features") + 1] == "rbf"
    assert argv[argv.index("--wait-value") + 1] == "stop"
