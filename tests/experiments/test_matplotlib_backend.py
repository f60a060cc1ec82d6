"""Library modules never choose the user's matplotlib backend (notebook figures must display)."""

from __future__ import annotations

import pkgutil
import subprocess
import sys

import hgpdm_torch.experiments as experiments


def test_importing_experiments_keeps_the_backend():
    names = [
        f"hgpdm_torch.experiments.{m.name}" for m in pkgutil.iter_modules(experiments.__path__)
    ]
    code = (
        "import importlib, matplotlib\n"
        "matplotlib.use('svg')\n"
        f"for name in {names!r}:\n"
        "    importlib.import_module(name)\n"
        "    assert matplotlib.get_backend() == 'svg', name\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-2000:]


def test_latent_plot_keeps_the_backend(tmp_path):
    import matplotlib

    from hgpdm_torch.datasets import styled_movements
    from hgpdm_torch.experiments.style_discovery import plot_latents
    from hgpdm_torch.models import GPDM

    backend = matplotlib.get_backend()
    matplotlib.use("svg")
    try:
        plot_latents({"GPDM": GPDM(styled_movements(1, 2, 8, 3).sequences, 2)}, tmp_path / "l.png")
        assert matplotlib.get_backend() == "svg"
    finally:
        matplotlib.use(backend)
    assert (tmp_path / "l.png").stat().st_size > 1000
