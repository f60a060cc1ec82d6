"""Folders in place of files are refused when the arguments are parsed (issue 54, finding 9): a
folder named like one of ``--out``'s results, or a folder where a reward-cache file belongs,
ends in a usage error naming the path before anything is simulated, not in an
``IsADirectoryError`` once the run is over."""

from __future__ import annotations

import pytest

from hgpdm_torch import cli
from hgpdm_torch.experiments import anticipation, demo

DEMO_FILES = ("demo.json", "return_rates.png", "rally.png")
ANTICIPATION_FILES = (
    "fig4_6.json",
    "fig4_7.json",
    "fig4_6_returns.png",
    "fig4_7_sample_efficiency.png",
)


@pytest.fixture
def no_run(monkeypatch):
    """The experiments must not start: a usage error comes first."""

    def refuse(*args, **kwargs):
        raise AssertionError("the experiment ran before its arguments were refused")

    monkeypatch.setattr(demo, "run_demo", refuse)
    monkeypatch.setattr(anticipation, "run_experiment", refuse)


def _usage_error(argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as stop:
        cli.main(argv)
    assert stop.value.code == 2
    return capsys.readouterr().err


@pytest.mark.parametrize(
    "command,name",
    [("demo", n) for n in DEMO_FILES]
    + [("anticipation", n) for n in ANTICIPATION_FILES]
    + [("demo --full", n) for n in ANTICIPATION_FILES],  # --full saves anticipation's files
)
def test_a_folder_named_like_an_output_file_is_refused_at_parse_time(
    command, name, tmp_path, capsys, no_run
):
    (tmp_path / name).mkdir()
    err = _usage_error([*command.split(), "--out", str(tmp_path)], capsys)
    assert f"argument --out: {tmp_path / name} is a folder" in err


class Ran(Exception):
    """Raised by a stand-in experiment: the arguments were accepted."""


def test_demo_without_full_does_not_check_anticipation_files(tmp_path, monkeypatch):
    """Only the files a command writes are checked."""
    pytest.importorskip("sapien")
    (tmp_path / "fig4_6.json").mkdir()

    def accepted(**kwargs):
        raise Ran

    monkeypatch.setattr(demo, "run_demo", accepted)
    with pytest.raises(Ran):
        cli.main(["demo", "--out", str(tmp_path), "--cache-dir", str(tmp_path / "cache")])


@pytest.mark.parametrize("command", ["demo", "anticipation"])
def test_a_folder_in_place_of_a_reward_cache_file_is_refused_at_parse_time(
    command, tmp_path, capsys, no_run
):
    pytest.importorskip("sapien")
    from hgpdm_torch.robots.table_tennis import trials

    folder = tmp_path / "cache" / "table_tennis" / "rewards" / trials._settings_key(None, None)
    blocked = folder / "0123456789abcdef01234567.json"
    blocked.mkdir(parents=True)
    err = _usage_error(
        [command, "--out", str(tmp_path / "out"), "--cache-dir", str(tmp_path / "cache")], capsys
    )
    assert f"argument --cache-dir: reward cache: {blocked} is a folder" in err


def test_the_default_reward_cache_is_checked_too(tmp_path, capsys, monkeypatch, no_run):
    pytest.importorskip("sapien")
    monkeypatch.setenv("HGPDM_CACHE", str(tmp_path))
    (tmp_path / "table_tennis").write_text("in the way")
    err = _usage_error(["demo", "--out", str(tmp_path / "out")], capsys)
    assert f"reward cache: {tmp_path / 'table_tennis'} is a file" in err
