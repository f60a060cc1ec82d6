"""The accelerator check in one command: ``make gpu-check`` (``python -m benchmarks.gpu_check``).

Where CUDA is available it runs, on the first GPU:

1. the GPU tests: every test marked ``gpu`` (the ``cuda`` half of the ``device`` fixture), which
   compare each computation on the GPU with the CPU float64 result;
2. the device benchmarks at their accelerator sizes (``--gpu-sizes``), in float64 and float32:
   online intention inference for B = 1 ... 4096 streams at the thesis size (N = 500, K = 25),
   the GPDM loss + gradient at N = 1,000 ... 10,000, moment matching at N = 500 for
   B = 1 ... 1024, Monte-Carlo planning with 500 ... 10,000 particles.

Each benchmark writes ``benchmarks/results/gpu_<name>_cuda_<dtype>.json`` (the device's name in
its ``meta``), and this check writes ``benchmarks/results/gpu_check.json``: the device, the
versions, each step's command, status and wall time, the test counts. The docs' performance page
is generated from these files.

Without CUDA it says so and runs the same code paths on the CPU at tiny sizes (the CPU half of
the same tests, the benchmarks' ``--quick`` sizes, in this process) in about a minute, writing
``gpu_check_quick.json`` and ``gpu_*_quick.json`` (ignored by git): a test runs this mode, so
the script itself cannot rot while no GPU is at hand.

Every step runs in its own process with the time left of ``--budget`` seconds (default 480), so
a step that hangs or fails is recorded and the others still run; the exit status is 1 when any
step failed or ran out of time. ``--only STEP ...`` (``tests`` or ``NAME:DTYPE``, e.g.
``mcp:float32``) reruns those steps alone and replaces them in the summary of the same device,
keeping the others; each step records its own date.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import re
import subprocess
import sys
import threading
import time
import traceback
from collections import deque
from pathlib import Path

import torch

from benchmarks.__main__ import main as benchmarks_main
from benchmarks._common import RESULTS, environment

ROOT = Path(__file__).resolve().parent.parent

#: the benchmarks the check runs, each in float64 and float32 (``benchmarks.__main__``'s
#: ``DEVICE_AWARE`` less ``variational``, whose accelerator sizes are those of the CPU)
BENCHMARKS = ("online_intention", "hgpdm_fit", "moment_matching", "mcp")
DTYPES = ("float64", "float32")

#: the test modules holding ``gpu`` tests; only they are collected, so that the check does not
#: import the simulator's test modules on a GPU machine without SAPIEN.
#: ``tests/test_benchmarks.py`` checks that no other module holds one.
GPU_TEST_FILES = ("tests/test_device.py", "tests/models/test_linear_iddm.py")

_COUNTS = re.compile(r"(\d+) (passed|failed|skipped|error|errors|deselected|xfailed|xpassed)")


def _run_step(name: str, command: list[str], deadline: float) -> dict[str, object]:
    """Run ``command`` in the repository root until it ends or ``deadline`` (``time.monotonic``)
    passes; its output goes to this process's, and its status, wall time and last lines are
    returned."""
    print(f"\n== gpu-check: {name}: {' '.join(command)}", flush=True)
    start, left = time.monotonic(), deadline - time.monotonic()
    date = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    if left <= 0:
        return {"step": name, "command": command, "status": "not run (no time left)"}
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    lines: deque[str] = deque(maxlen=40)

    def echo() -> None:  # in a thread, so that a silent step still meets its deadline
        assert proc.stdout is not None
        for line in proc.stdout:
            print(line, end="", flush=True)
            lines.append(line.rstrip())

    reader = threading.Thread(target=echo, daemon=True)
    reader.start()
    try:
        proc.wait(timeout=left)
        status = "ok" if proc.returncode == 0 else f"failed (exit {proc.returncode})"
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        status = "timed out"
    reader.join(timeout=5.0)
    return {
        "step": name,
        "date": date,
        "command": command,
        "status": status,
        "seconds": round(time.monotonic() - start, 1),
        "tail": list(lines)[-12:],
    }


def _run_inline(name: str, command: list[str], deadline: float) -> dict[str, object]:
    """``python -m benchmarks NAME ARGS`` (``command``) in this process: what
    :func:`_run_step` returns, less the output's tail."""
    print(f"\n== gpu-check: {name}: {' '.join(command)}", flush=True)
    date = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    step: dict[str, object] = {"step": name, "date": date, "command": command}
    if time.monotonic() > deadline:
        return {**step, "status": "not run (no time left)"}
    start = time.monotonic()
    try:
        code = benchmarks_main(command[3:])
        status = "ok" if code == 0 else f"failed (exit {code})"
    except Exception as err:  # recorded like a failed process; the other steps still run
        traceback.print_exc()
        status = f"failed ({type(err).__name__}: {err})"
    return {**step, "status": status, "seconds": round(time.monotonic() - start, 1)}


def _gpu_test_ids(cuda: bool) -> list[str]:
    """Node ids of the ``gpu`` tests, or, without CUDA, of their CPU halves (``[cuda`` ->
    ``[cpu``): the same code on the CPU."""
    out = subprocess.run(
        [sys.executable, "-m", "pytest", "--co", "-q", "-m", "gpu", *GPU_TEST_FILES],
        cwd=ROOT, capture_output=True, text=True, check=False,
    )  # fmt: skip
    ids = [line for line in out.stdout.splitlines() if "::" in line]
    if not ids:
        raise RuntimeError(f"no gpu test collected from {GPU_TEST_FILES}:\n{out.stdout[-2000:]}")
    return ids if cuda else [i.replace("[cuda", "[cpu") for i in ids]


def device_info(cuda: bool) -> dict[str, object]:
    """The device the check ran on: name, memory, compute capability, CUDA and driver."""
    info: dict[str, object] = {**environment(), "cuda": cuda}
    if cuda:
        props = torch.cuda.get_device_properties(0)
        info |= {
            "device": torch.cuda.get_device_name(0),
            "memory [GiB]": round(props.total_memory / 2**30, 1),
            "compute capability": f"{props.major}.{props.minor}",
            "multiprocessors": props.multi_processor_count,
            "cuda runtime": torch.version.cuda,
        }
        smi = subprocess.run(
            ["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
            capture_output=True, text=True, check=False,
        )  # fmt: skip
        if smi.returncode == 0:
            info["driver"] = smi.stdout.strip()
    else:
        info["device"] = "cpu (no CUDA: the same code paths at tiny sizes)"
    return info


def _step_names() -> list[str]:
    return ["tests"] + [f"{name}:{dtype}" for dtype in DTYPES for name in BENCHMARKS]


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.gpu_check")
    parser.add_argument(
        "--budget", type=float, default=480.0, help="seconds for the whole check (default 480)"
    )
    parser.add_argument(
        "--cpu", action="store_true", help="the CPU mode (tiny sizes) even where CUDA is present"
    )
    parser.add_argument(
        "--only", nargs="+", choices=_step_names(), metavar="STEP",
        help=f"rerun these steps alone, keeping the others in the summary: {_step_names()}",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if not args.budget > 0:
        parser.error(f"--budget must be a positive number of seconds, got {args.budget}")
    cuda = torch.cuda.is_available() and not args.cpu
    if not cuda:
        print(
            "gpu-check: no CUDA device (or --cpu): running the same code paths on the CPU at "
            "tiny sizes; nothing here measures a GPU",
            flush=True,
        )
    deadline = time.monotonic() + args.budget
    out = RESULTS / ("gpu_check.json" if cuda else "gpu_check_quick.json")
    summary: dict[str, object] = {"meta": device_info(cuda), "steps": []}
    if args.only and out.exists():  # keep the other steps of an earlier check on this device
        earlier = json.loads(out.read_text())
        if earlier.get("meta", {}).get("device") == summary["meta"]["device"]:
            kept = set(_step_names()) - set(args.only)
            summary["steps"] = [s for s in earlier["steps"] if s.get("key") in kept]
    steps: list[dict[str, object]] = summary["steps"]  # type: ignore[assignment]

    def record(key: str, step: dict[str, object]) -> None:
        steps.append({"key": key, **step})
        steps.sort(key=lambda s: _step_names().index(str(s.get("key"))))
        out.write_text(json.dumps(summary, indent=1) + "\n")  # after each step: a kill keeps it

    todo = args.only or _step_names()
    if "tests" in todo:
        tests = _run_step(
            "gpu tests" if cuda else "gpu tests, CPU half",
            [sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider",
             *_gpu_test_ids(cuda)],
            deadline,
        )  # fmt: skip
        tests["counts"] = {k: int(n) for n, k in _COUNTS.findall(" ".join(tests.get("tail", [])))}
        record("tests", tests)
    device = "cuda" if cuda else "cpu"
    for key in (k for k in _step_names()[1:] if k in todo):
        name, dtype = key.split(":")
        size = ["--gpu-sizes"] if cuda else ["--gpu-sizes", "--quick"]
        command = [sys.executable, "-m", "benchmarks", name, "--device", device,
                   "--dtype", dtype, *size]  # fmt: skip
        if cuda:
            step = _run_step(f"{name} {dtype}", command, deadline)
        else:  # tiny sizes: in this process, without paying a process start per step
            step = _run_inline(f"{name} {dtype}", command, deadline)
        tag = "" if cuda else "_quick"
        step["results"] = f"benchmarks/results/gpu_{name}_{device}_{dtype}{tag}.json"
        record(key, step)
    failed = [s["step"] for s in steps if s.get("status") != "ok"]
    print(f"\ngpu-check on {summary['meta']['device']}: {len(steps) - len(failed)} of "
          f"{len(steps)} steps ok" + (f"; not ok: {failed}" if failed else "") +
          f"; summary in {out.relative_to(ROOT)}")  # fmt: skip
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
