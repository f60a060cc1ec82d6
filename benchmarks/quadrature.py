"""Accuracy of the Gauss-Hermite expectations of kernels without closed forms.

``python -m benchmarks quadrature [--quick]``. Writes ``benchmarks/results/quadrature.json``
(``quadrature_quick.json`` with ``--quick``). For Matern-3/2 and 5/2, periodic and rational
quadratic kernels (unit scale, length scale 1; period 2) at input Gaussians ``N(mu, s^2 I)`` in D
= 1, 2, 3 Gaussian dims, the largest error of ``psi1 = E[k(x, X_i)]`` and ``psi2 =
E[k(x, X_i) k(x, X_j)]`` over 20 training points ``X ~ N(0, I)``, with the default rule
(:func:`hgpdm_torch.quadrature.default_points`: 8, 8, 6 points per dim), against a reference
rule of 60, 24, 12 points per dim. ``s / l_eff`` is the input's sd over the kernel's effective
length scale (``l``; ``l p / (2 pi)`` for the periodic kernel, whose exponent is
``-2 sin^2(pi r / p) / l^2 ~ -r^2 / (2 (l p / 2 pi)^2)``). ``ref - MC`` checks the reference
itself: its largest ``psi1`` difference from Monte Carlo of the gpytorch kernel (4e5 draws, a
standard error of about 1e-3), so the errors below it are the rule's own only where the
reference is converged (it is for every row with ``s / l_eff <= 1``).
"""

from __future__ import annotations

import math

import torch
from gpytorch.kernels import MaternKernel, PeriodicKernel, RQKernel

from benchmarks._common import Options, parse_options
from hgpdm_torch import expectations, settings
from hgpdm_torch.quadrature import default_points
from hgpdm_torch.results import ResultTable

REFERENCE_POINTS = {1: 60, 2: 24, 3: 12}


def _kernel(name: str):
    if name.startswith("matern"):
        kernel = MaternKernel(nu=int(name[-2]) / 2)
        kernel.lengthscale = 1.0
        return kernel, 1.0
    if name == "periodic":
        kernel = PeriodicKernel()
        kernel.lengthscale, kernel.period_length = 1.0, 2.0
        return kernel, 2.0 / (2 * math.pi)
    kernel = RQKernel()
    kernel.lengthscale, kernel.alpha = 1.0, 1.0
    return kernel, 1.0


def run(opts: Options, dims: list[int], ratios: list[float], draws: int) -> ResultTable:
    table = ResultTable(
        "Gauss-Hermite kernel expectations: largest error of psi1 and psi2 (unit-scale kernels) "
        "with the default rule against a reference rule, float64",
        ["kernel", "D", "points", "s / l_eff", "psi1 error", "psi2 error", "ref - MC"],
        meta={**opts.meta(), "reference points": REFERENCE_POINTS, "MC draws": draws},
    )
    gen = torch.Generator().manual_seed(0)
    for d in dims:
        X = torch.randn(20, d, generator=gen, dtype=torch.float64)
        mu = 0.5 * torch.randn(d, generator=gen, dtype=torch.float64)
        for name in ("matern32", "matern52", "periodic", "rq"):
            kernel, scale = _kernel(name)
            kernel = kernel.to(torch.float64)
            for ratio in ratios:
                sd = ratio * scale
                Sigma = sd**2 * torch.eye(d, dtype=torch.float64)
                with torch.no_grad():
                    p1 = expectations.psi1(kernel, mu, Sigma, X)
                    p2 = expectations.psi2(kernel, mu, Sigma, X)
                    with settings.quadrature_points(REFERENCE_POINTS[d]):
                        r1 = expectations.psi1(kernel, mu, Sigma, X)
                        r2 = expectations.psi2(kernel, mu, Sigma, X)
                    xs = mu + sd * torch.randn(draws, d, generator=gen, dtype=torch.float64)
                    mc = kernel(xs, X).to_dense().mean(0)
                table.add(
                    **{
                        "kernel": name,
                        "D": d,
                        "points": default_points(d),
                        "s / l_eff": ratio,
                        "psi1 error": float((p1 - r1).abs().max()),
                        "psi2 error": float((p2 - r2).abs().max()),
                        "ref - MC": float((r1 - mc).abs().max()),
                    }
                )
                print(table.rows[-1], flush=True)
    return table


def main(argv: list[str]) -> int:
    opts = parse_options(argv, "python -m benchmarks quadrature")
    torch.set_num_threads(1)
    if opts.quick:
        table = run(opts, [1], [0.3], draws=10_000)
    else:
        table = run(opts, [1, 2, 3], [0.1, 0.3, 1.0], draws=400_000)
    print(table.to_markdown())
    table.to_json(opts.results_file("quadrature"))
    return 0
