"""The reward cache never lies (issue 54, findings 4 and 9): a checksum of each file's content and
the simulation it came from, rejected files simulated again with one warning per table, and a
folder where a cache file belongs refused before anything is simulated.

No SAPIEN run: a fake executor stands in for the simulator and records what it is asked.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import numpy as np
import pytest

from hgpdm_torch.parallel import SerialExecutor
from hgpdm_torch.robots.table_tennis import trials as T
from hgpdm_torch.robots.table_tennis.trials import reward_table

ACTIONS = ("forehand", "backhand")
STARTS = (-0.24, -0.08)


class FakeSimulator(SerialExecutor):
    """Returns +1 for the forehand and -1 for the backhand without running SAPIEN, and keeps the
    jobs it was given (one per ball whose cells are missing from the cache)."""

    def __init__(self) -> None:
        self.jobs: list[tuple] = []

    def map(self, fn: Callable, items: Iterable) -> Iterator:
        items = list(items)
        self.jobs += items
        return iter(
            [np.array([1 if a == "forehand" else -1 for a, _ in job[3]], np.int8) for job in items]
        )


@pytest.fixture(scope="module")
def trials() -> T.Trials:
    return T.make_trials(3, seed=7)


def _table(trials, cache, sim=None):
    return reward_table(trials, ACTIONS, STARTS, executor=sim or FakeSimulator(),
                        cache_dir=cache, progress=False)  # fmt: skip


def _files(cache: Path) -> list[Path]:
    return sorted((cache / "table_tennis" / "rewards").glob("*/*.json"))


def _cache_warnings(caught) -> list[str]:
    return [str(w.message) for w in caught if "reward cache" in str(w.message)]


def test_cache_files_carry_a_checksum_and_the_simulation_version(trials, tmp_path):
    _table(trials, tmp_path)
    files = _files(tmp_path)
    assert len(files) == 3
    data = json.loads(files[0].read_text())
    assert data["simulation"] == T._simulation_fingerprint()
    assert len(data["sha256"]) == 64 and set(data["sha256"]) <= set("0123456789abcdef")
    assert data["cells"] == {"backhand@-0.08": -1, "backhand@-0.24": -1,
                             "forehand@-0.08": 1, "forehand@-0.24": 1}  # fmt: skip
    # read back: nothing is simulated again, nothing is warned
    sim = FakeSimulator()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again = _table(trials, tmp_path, sim)
    assert sim.jobs == [] and again[:, 0].eq(1).all() and again[:, 1].eq(-1).all()
    assert not list(tmp_path.rglob("*.tmp"))  # the atomic writes leave no temporary file


def _negate(path: Path) -> None:
    """Every reward of a cache file negated by hand: still valid JSON, checksum left as it was."""
    data = json.loads(path.read_text())
    data["cells"] = {k: -v for k, v in data["cells"].items()}
    path.write_text(json.dumps(data))


def test_a_file_whose_checksum_fails_is_simulated_again_with_one_warning(trials, tmp_path):
    """Finding 4: negated rewards were used as they were."""
    truth = _table(trials, tmp_path)
    for path in _files(tmp_path):
        _negate(path)
    sim = FakeSimulator()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        table = _table(trials, tmp_path, sim)
    assert np.array_equal(table, truth)
    assert len(sim.jobs) == 3  # every ball simulated again
    (message,) = _cache_warnings(caught)  # one warning for the table, not one per file
    folder = _files(tmp_path)[0].parent
    assert str(folder) in message and "3 of 3 files" in message and "checksum" in message
    # the files were rewritten with a valid checksum: the next table trusts them
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sim = FakeSimulator()
        assert np.array_equal(_table(trials, tmp_path, sim), truth) and sim.jobs == []


def test_a_file_of_the_old_format_is_simulated_again_once(trials, tmp_path):
    """A cache written before the checksum (``{"cell": reward}``) is not trusted: it is simulated
    again once, with one warning, and rewritten in the current format."""
    truth = _table(trials, tmp_path)
    files = _files(tmp_path)
    for path in files[:2]:  # flipped rewards: the file is not what is returned
        cells = json.loads(path.read_text())["cells"]
        path.write_text(json.dumps({k: -v for k, v in cells.items()}, sort_keys=True))
    sim = FakeSimulator()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert np.array_equal(_table(trials, tmp_path, sim), truth)
    assert len(sim.jobs) == 2
    (message,) = _cache_warnings(caught)
    assert "2 of 3 files" in message and "older" in message and str(files[0].parent) in message
    assert all("sha256" in json.loads(p.read_text()) for p in files)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sim = FakeSimulator()
        _table(trials, tmp_path, sim)
    assert sim.jobs == []


@pytest.mark.parametrize(
    "edit",
    [
        lambda d: d.update(simulation="0" * 16),  # from another version of the simulation
        lambda d: d["cells"].update({"forehand@-0.24": 2}),  # not a reward
        lambda d: d.pop("sha256"),
    ],
)
def test_any_edit_is_rejected(trials, tmp_path, edit):
    truth = _table(trials, tmp_path)
    path = _files(tmp_path)[0]
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))
    sim = FakeSimulator()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert np.array_equal(_table(trials, tmp_path, sim), truth)
    assert len(sim.jobs) == 1 and len(_cache_warnings(caught)) == 1


def test_a_folder_in_place_of_a_cache_file_is_refused_before_simulating(trials, tmp_path):
    """Finding 9: a raw IsADirectoryError from os.replace after simulating."""
    folder = tmp_path / "table_tennis" / "rewards" / T._settings_key(None, None)
    blocked = folder / f"{trials.fingerprints()[1]}.json"
    blocked.mkdir(parents=True)
    sim = FakeSimulator()
    with pytest.raises(ValueError, match="is a folder") as err:
        _table(trials, tmp_path, sim)
    assert str(blocked) in str(err.value)
    assert sim.jobs == []  # nothing simulated before the refusal
    with pytest.raises(ValueError, match="is a folder") as err:
        T.check_cache_dir(tmp_path)
    assert str(blocked) in str(err.value)


def test_a_file_in_place_of_a_cache_folder_is_refused(trials, tmp_path):
    (tmp_path / "table_tennis").write_text("not a folder")
    sim = FakeSimulator()
    with pytest.raises(ValueError, match="is a file") as err:
        _table(trials, tmp_path, sim)
    assert str(tmp_path / "table_tennis") in str(err.value) and sim.jobs == []
