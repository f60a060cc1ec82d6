"""hgpdm_torch.parallel: serial, local-process and Ray executors return the same results in order.

The Ray tests start one real local Ray instance per module (about 15 s) and are skipped, with the
reason, when Ray is not installed. The missing-Ray error is tested by hiding the installed module.
"""

from __future__ import annotations

import importlib.util
import os
import pickle
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Iterator

import pytest
import torch

from hgpdm_torch import cli
from hgpdm_torch.parallel import (
    Executor,
    ProcessExecutor,
    RayExecutor,
    SerialExecutor,
    available_cpus,
    check_ray_address,
    get_executor,
)

HAS_RAY = importlib.util.find_spec("ray") is not None
NO_RAY = "Ray is not installed (pip install 'hgpdm-torch[cluster]')"
needs_ray = pytest.mark.skipif(not HAS_RAY, reason=NO_RAY)
if HAS_RAY:
    # Ray's log handler keeps the sys.stderr of the moment Ray is imported; imported inside a
    # test, that is the test's capture, closed afterwards ("--- Logging error ---" later on).
    importlib.import_module("ray")


def value(seed: int) -> list[float]:
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(3, generator=gen, dtype=torch.float64).tolist()  # not the default dtype


def draw(seed: int) -> list[float]:
    """A seeded job that takes longer the larger ``seed % 4`` (results arrive out of order)."""
    time.sleep(0.05 * (seed % 4))
    return value(seed)


def fail_on_three(x: int) -> int:
    if x == 3:
        raise ValueError("job 3 failed")
    return x


class Refusing(Executor):
    """An executor that must not be asked for anything (everything is cached)."""

    workers = 1

    def map(self, fn: Callable, items: Iterable) -> Iterator:
        raise AssertionError(f"asked to run {list(items)}")

    def close(self) -> None:
        pass


def unused_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def latent_norm(model, test, labels) -> float:
    """A cross-validation score that depends on the fit: the fitted latents' norm."""
    return float(model.latent.detach().norm())


SEEDS = [3, 2, 1, 0, 7, 6, 5, 4]
EXPECTED = [value(s) for s in SEEDS]


@pytest.fixture(scope="module")
def ray_local() -> Iterator[Executor]:
    """One real local Ray instance with 2 CPUs for the module, shut down afterwards."""
    if not HAS_RAY:
        pytest.skip(NO_RAY)
    with get_executor(2, "local") as executor:
        yield executor


def test_get_executor_chooses_by_workers_and_address() -> None:
    assert isinstance(get_executor(1), SerialExecutor)
    with get_executor(2) as ex:
        assert isinstance(ex, ProcessExecutor) and ex.workers == 2
    with get_executor() as ex:
        assert ex.workers == available_cpus()
    for bad in (0, -2, True, 1.5, "2"):
        with pytest.raises(ValueError, match="workers"):
            get_executor(bad)  # type: ignore[arg-type]
    for good in ("auto", "local", " 10.0.0.2:6379", "head:6379", "ray://head:10001", "[::1]:6379"):
        assert check_ray_address(good) == good.strip()
    for bad in ("", "head", "head:0", "head:65536", "::1:6379", "http://head:1", "a b:1", "x:y"):
        with pytest.raises(ValueError, match="ray_address must be"):
            get_executor(2, bad)
    with pytest.raises(TypeError, match="ray_address"):
        get_executor(2, 6379)  # type: ignore[arg-type]


def test_importing_the_package_does_not_import_ray() -> None:
    code = (
        "import sys, hgpdm_torch, hgpdm_torch.parallel as p\n"
        "p.get_executor(2).close()\n"
        "assert 'ray' not in sys.modules, 'ray was imported'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


#: a parent whose torch has run its 2-thread intra-op pool, then jobs doing a matrix product with
#: 2 threads in a local worker: a forked worker inherits the pool's locks and hangs in its first
#: product (3 of 3 runs with the fork start method on the 2-core machine); a spawned one cannot
THREADS_THEN_WORKERS = """
from functools import partial

import torch
from hgpdm_torch.parallel import ProcessExecutor
from hgpdm_torch.results import ResultTable  # noqa: F401  (a package import, as the CLI)

torch.set_num_threads(2)
x = torch.randn(800, 800, dtype=torch.float64)
for _ in range(3):
    x = (x @ x) / 800.0
eye = torch.eye(400, dtype=torch.float64)
with ProcessExecutor(1) as ex:  # one worker: it takes both cores' threads, as the parent did
    print([float(r.trace()) for r in ex.map(partial(torch.mm, eye), [eye] * 4)])
"""


def test_workers_started_after_torch_threads_finish() -> None:
    """The executor is safe after torch has started threads, without OMP_NUM_THREADS=1 (the
    Makefile sets it; a user running ``hgpdm ...`` directly does not)."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    out = subprocess.run(
        [sys.executable, "-c", THREADS_THEN_WORKERS],
        env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[400.0, 400.0, 400.0, 400.0]"  # trace(I I), from each job


def test_an_unpicklable_job_raises_instead_of_hanging() -> None:
    with ProcessExecutor(2) as ex, pytest.raises(TypeError, match="picklable fn"):
        list(ex.map(lambda x: x, range(3)))
    with ProcessExecutor(2) as ex:  # an unpicklable item: its error when its result is read
        results = ex.map(str, [1, lambda: 2])
        assert next(results) == "1"
        with pytest.raises((pickle.PicklingError, AttributeError, TypeError)):
            next(results)


@pytest.mark.parametrize("workers", [1, 2])
def test_local_executors_keep_order_and_results(workers: int) -> None:
    with get_executor(workers) as ex:
        assert list(ex.map(draw, SEEDS)) == EXPECTED
        assert list(ex.map(draw, iter(SEEDS[:3]))) == EXPECTED[:3]  # reused, any iterable
        assert list(ex.map(draw, [])) == []
        results = ex.map(fail_on_three, range(5))
        assert [next(results) for _ in range(3)] == [0, 1, 2]
        with pytest.raises(ValueError, match="job 3 failed"):
            next(results)


def test_missing_ray_says_how_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` now fails as if not installed
    for address in ("local", "auto", "127.0.0.1:6379"):
        with pytest.raises(ImportError, match=r"pip install 'hgpdm-torch\[cluster\]'"):
            get_executor(2, address)


@needs_ray
def test_unreachable_address_fails_fast(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    address = f"127.0.0.1:{unused_port()}"
    start = time.perf_counter()
    with pytest.raises(ConnectionError, match=f"no Ray cluster answers at ray_address={address} "):
        get_executor(2, address, timeout=3)
    with pytest.raises(ConnectionError, match="no Ray cluster answers"):
        RayExecutor(f"ray://{address}", timeout=3)
    monkeypatch.setenv("RAY_ADDRESS", address)  # "auto" follows $RAY_ADDRESS
    with pytest.raises(ConnectionError, match=address):
        get_executor(2, "auto", timeout=3)
    assert time.perf_counter() - start < 20
    # the commands turn it into a usage error naming the option, before simulating anything
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["anticipation", "--ray-address", address])
    assert exit_info.value.code == 2
    assert "argument --ray-address: no Ray cluster answers" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["demo", "--ray-address", "head"])
    assert "argument --ray-address: ray_address must be" in capsys.readouterr().err


@needs_ray
def test_ray_matches_serial_and_local_processes(ray_local: Executor, tmp_path) -> None:
    """One test for everything that needs the Ray instance: pytest-xdist hands consecutive
    tests to different workers, and each worker would start its own instance."""
    from hgpdm_torch.robots.table_tennis.opponent import OpponentConfig
    from hgpdm_torch.robots.table_tennis.trials import make_trials, reward_table

    def slow_square(x: int) -> int:  # a closure: Ray ships it by value
        time.sleep(0.05 * (x % 4))
        return x * x

    assert list(ray_local.map(draw, SEEDS)) == EXPECTED
    assert list(ray_local.map(slow_square, range(8))) == [x * x for x in range(8)]
    assert list(ray_local.map(draw, [])) == []
    with pytest.raises(ValueError, match="job 3 failed"):
        list(ray_local.map(fail_on_three, range(5)))
    # A second executor in a process already connected to Ray reuses the connection (at most
    # one task in flight here) and leaves it open when closed.
    address = importlib.import_module("ray").get_runtime_context().gcs_address
    with RayExecutor(address, workers=1) as one_at_a_time:
        assert list(one_at_a_time.map(draw, SEEDS)) == EXPECTED
    assert list(ray_local.map(draw, SEEDS[:2])) == EXPECTED[:2]

    # a cross-validation fold loop (issue: scale-out of the CV loops) on Ray: the serial table
    from hgpdm_torch import cross_validate
    from hgpdm_torch.datasets import styled_movements
    from hgpdm_torch.models import HGPDM

    moves = styled_movements(num_styles=2, per_style=2, length=12, obs_dim=4, seed=0)
    kw = dict(labels=moves.labels, fixed={"latent_dim": 2}, fit_steps=3, seed=1)
    serial_cv = cross_validate(HGPDM, moves.sequences, latent_norm, **kw)
    ray_cv = cross_validate(HGPDM, moves.sequences, latent_norm, executor=ray_local, **kw)
    assert ray_cv.table.rows == serial_cv.table.rows and ray_cv.fold_scores == serial_cv.fold_scores

    # a real reward table (SAPIEN) in this process, in 2 local processes and on Ray
    config = OpponentConfig(late_change_prob=0.0)
    trials = make_trials(2, seed=7, targets=[0.75, -0.75], config=config)
    kw = dict(actions=("forehand",), start_times=(-0.24,), progress=False)
    serial = reward_table(trials, **kw, cache_dir=tmp_path / "serial")
    with get_executor(2) as processes:
        local = reward_table(trials, **kw, executor=processes, cache_dir=tmp_path / "processes")
    on_ray = reward_table(trials, **kw, executor=ray_local, cache_dir=tmp_path / "ray")
    assert serial.flatten().tolist() == [1, -1]  # forehand returns the right, misses the left
    assert torch.equal(serial, local) and torch.equal(serial, on_ray)
    # what Ray cached is read back on any executor: no cell is simulated again
    again = reward_table(trials, **kw, executor=Refusing(), cache_dir=tmp_path / "ray")
    assert torch.equal(again, serial)
