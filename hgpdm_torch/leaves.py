r"""Kernels as sums of leaves: the closed-form dispatch of the Gaussian-input expectations.

:func:`kernel_leaves` rewrites a gpytorch kernel as a sum of :class:`Leaf` terms over all input
columns, dispatching on the kernel type as GPflow does (:func:`register_leaves`): ``RBFKernel``
(ARD or not), ``LinearKernel``, ``ScaleKernel``, ``AdditiveKernel``, ``ProductKernel``,
``active_dims``, and the toolkit's ``DiscreteIntentionKernel``, ``IntentionRBFKernel`` and
``DenseLinearKernel``. Each leaf is ``coef * exp(-1/2 sum_c w_c (x_c - x'_c)^2)`` or
``coef * sum_c w_c x_c x'_c``, times Kronecker deltas on code columns and, from a product, times
linear factors (``Leaf.factors``). Any other kernel (or a subclass with its own ``forward``) is
one ``"kernel"`` leaf that :mod:`hgpdm_torch.quadrature` integrates.
:mod:`hgpdm_torch.expectations` turns the leaves into terms and their expectations.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import singledispatch

import gpytorch.kernels as gk
import torch

from .kernels import DenseLinearKernel, DiscreteIntentionKernel, IntentionRBFKernel

__all__ = ["Leaf", "kernel_leaves", "register_leaves"]


@dataclass(frozen=True)
class Leaf:
    """One additive term of a kernel over all ``Din`` input columns.

    Attributes:
        kind: ``"rbf"`` (``coef exp(-1/2 sum_c w_c (x_c - x'_c)^2)``), ``"linear"``
            (``coef sum_c w_c x_c x'_c``) or ``"kernel"`` (``coef kernel(x[columns],
            x'[columns])``, a kernel without closed forms, integrated by quadrature).
        coef: scalar tensor, product of the enclosing ``ScaleKernel`` output scales.
        weight: ``[Din]`` inverse squared length scales (rbf) or variances (linear); zero on
            columns the term does not read.
        cols: the columns the term reads (structural, independent of the weight values).
        codes: columns holding discrete codes; the term is multiplied by ``delta(x_c, x'_c)``.
        factors: linear leaves (unit ``coef``, no codes, no factors) the term is multiplied by,
            from a ``ProductKernel`` (RBF parts of a product are merged into one RBF leaf, so
            these are never RBFs unless the product has a ``"kernel"`` part, which then heads
            the leaf). Without a ``"kernel"`` part, each part must read known columns only,
            except at most one part (this leaf or a factor) over the Gaussian columns
            (:func:`split_terms`).
        kernel: the gpytorch kernel of a ``"kernel"`` leaf (its ``forward`` is evaluated).
        columns: the columns it reads, in its order.
    """

    kind: str
    coef: torch.Tensor
    weight: torch.Tensor
    cols: frozenset[int]
    codes: tuple[int, ...] = ()
    factors: tuple[Leaf, ...] = ()
    kernel: gk.Kernel | None = None
    columns: tuple[int, ...] = ()

    def parts(self) -> list[Leaf]:
        """The leaf without its factors, followed by its factors (whose product it is)."""
        return [replace(self, factors=()), *self.factors] if self.factors else [self]

    @property
    def opaque(self) -> bool:
        """Whether a part is a kernel without closed forms (the leaf is integrated by
        quadrature, :mod:`hgpdm_torch.quadrature`)."""
        return any(p.kind == "kernel" for p in self.parts())


def kernel_leaves(kernel: gk.Kernel, input_dim: int) -> list[Leaf]:
    """Rewrite ``kernel`` as a sum of :class:`Leaf` terms over ``input_dim`` input columns.

    Follows gpytorch's calling conventions: a kernel's ``active_dims`` selects columns when it is
    called (at the top level and inside ``AdditiveKernel``), while ``ScaleKernel`` and
    ``DiscreteIntentionKernel`` call their base kernel's ``forward`` on the columns they see.

    A kernel type registered with :func:`register_leaves` (RBF, linear, scale, sum, product and
    the intention kernels here) becomes its closed-form leaves; any other gpytorch kernel, or a
    subclass that overrides ``forward``, one ``"kernel"`` leaf integrated by quadrature.

    Raises:
        TypeError: ``kernel`` is not a gpytorch kernel.
        ValueError: for batched kernels or inconsistent dimensions.
    """
    if not isinstance(kernel, gk.Kernel):
        raise TypeError(f"kernel must be a gpytorch Kernel, got {type(kernel).__name__}")
    return _called(kernel, list(range(int(input_dim))), int(input_dim))


def _called(kernel: gk.Kernel, cols: list[int], din: int) -> list[Leaf]:
    if kernel.active_dims is not None:
        idx = [int(i) for i in kernel.active_dims.tolist()]
        if any(i < -len(cols) or i >= len(cols) for i in idx):
            raise ValueError(
                f"{type(kernel).__name__}.active_dims {idx} out of range for {len(cols)} columns"
            )
        cols = [cols[i] for i in idx]
    return _leaves(kernel, cols, din)


def _check_unbatched(kernel: gk.Kernel) -> None:
    if len(kernel.batch_shape) != 0:
        raise ValueError(
            f"{type(kernel).__name__} has batch_shape {tuple(kernel.batch_shape)}; Gaussian-input "
            "expectations support unbatched kernels only (batch the inputs instead)"
        )


def _scatter(values: torch.Tensor, cols: list[int], din: int) -> torch.Tensor:
    idx = torch.as_tensor(cols, dtype=torch.long, device=values.device)
    out = torch.zeros(din, dtype=values.dtype, device=values.device)
    return out.index_add(0, idx, values.reshape(-1).expand(len(cols)))


def _rbf_leaf(lengthscale: torch.Tensor, cols: list[int], din: int, name: str) -> Leaf:
    ls = lengthscale.reshape(-1)
    if ls.numel() not in (1, len(cols)):
        raise ValueError(
            f"{name} has {ls.numel()} length scales but sees {len(cols)} input columns"
        )
    w = _scatter(ls.pow(-2), cols, din)
    return Leaf("rbf", torch.ones((), dtype=w.dtype, device=w.device), w, frozenset(cols))


@singledispatch
def _closed(kernel: gk.Kernel, cols: list[int], din: int) -> list[Leaf]:
    """Any kernel without closed forms: one opaque leaf over the columns it sees."""
    _check_unbatched(kernel)
    one = torch.ones((), dtype=torch.get_default_dtype())
    for p in kernel.parameters():  # the coefficient in the kernel's dtype and on its device
        one = torch.ones((), dtype=p.dtype, device=p.device)
        break
    zeros = torch.zeros(din, dtype=one.dtype, device=one.device)
    return [Leaf("kernel", one, zeros, frozenset(cols), kernel=kernel, columns=tuple(cols))]


def _leaves(kernel: gk.Kernel, cols: list[int], din: int) -> list[Leaf]:
    owner = next(c for c in type(kernel).__mro__ if c in _closed.registry)
    if owner is not object and owner.forward is not type(kernel).forward:
        owner = object  # a subclass with its own forward: not the registered closed form
    return _closed.registry[owner](kernel, cols, din)


def register_leaves(kernel_type: type) -> object:
    """Decorator registering closed-form expectations for a kernel type, as GPflow's dispatch
    does: ``fn(kernel, cols, din) -> list[Leaf]`` rewrites a kernel seeing input columns
    ``cols`` (of ``din``) as RBF and linear :class:`Leaf` terms (see the handlers here).
    Subclasses that keep the type's ``forward`` use it too."""
    if not (isinstance(kernel_type, type) and issubclass(kernel_type, gk.Kernel)):
        raise TypeError(f"kernel_type must be a gpytorch Kernel subclass, got {kernel_type!r}")
    return _closed.register(kernel_type)


@_closed.register
def _(kernel: gk.RBFKernel, cols: list[int], din: int) -> list[Leaf]:
    _check_unbatched(kernel)
    return [_rbf_leaf(kernel.lengthscale, cols, din, "RBFKernel")]


@_closed.register
def _(kernel: IntentionRBFKernel, cols: list[int], din: int) -> list[Leaf]:
    _check_unbatched(kernel)
    if len(cols) != kernel.x_dim + kernel.g_dim:
        raise ValueError(
            f"IntentionRBFKernel expects {kernel.x_dim + kernel.g_dim} columns, sees {len(cols)}"
        )
    return [_rbf_leaf(kernel.lengthscale_vector(), cols, din, "IntentionRBFKernel")]


@_closed.register(gk.LinearKernel)
@_closed.register(DenseLinearKernel)
def _(kernel: gk.LinearKernel, cols: list[int], din: int) -> list[Leaf]:
    _check_unbatched(kernel)
    w = _scatter(kernel.variance.reshape(1), cols, din)
    return [Leaf("linear", torch.ones((), dtype=w.dtype, device=w.device), w, frozenset(cols))]


@_closed.register
def _(kernel: gk.ScaleKernel, cols: list[int], din: int) -> list[Leaf]:
    _check_unbatched(kernel)
    scale = kernel.outputscale.reshape(())
    return [
        replace(leaf, coef=leaf.coef * scale) for leaf in _leaves(kernel.base_kernel, cols, din)
    ]


@_closed.register
def _(kernel: gk.AdditiveKernel, cols: list[int], din: int) -> list[Leaf]:
    return [leaf for k in kernel.kernels for leaf in _called(k, cols, din)]


@_closed.register
def _(kernel: gk.ProductKernel, cols: list[int], din: int) -> list[Leaf]:
    # (sum_a leaf_a)(sum_b leaf_b) = sum_ab leaf_a leaf_b; each factor applies its active_dims
    out = _called(kernel.kernels[0], cols, din)
    for factor in kernel.kernels[1:]:
        out = [_leaf_product(a, b) for a in out for b in _called(factor, cols, din)]
    return out


def _leaf_product(a: Leaf, b: Leaf) -> Leaf:
    """The product of two leaves as one leaf: every RBF part merged into one RBF (precisions
    add, exactly), the linear parts kept as unit-coefficient factors of the first part."""
    parts = [*a.parts(), *b.parts()]
    coef, codes = a.coef * b.coef, (*a.codes, *b.codes)
    if any(p.kind == "kernel" for p in parts):  # evaluated part by part at quadrature nodes
        head = next(p for p in parts if p.kind == "kernel")
        rest = [replace(p, coef=torch.ones_like(p.coef), codes=()) for p in parts if p is not head]
        return replace(head, coef=coef, codes=codes, factors=tuple(rest))
    rbfs = [p for p in parts if p.kind == "rbf"]
    linears = [replace(p, coef=torch.ones_like(p.coef), codes=()) for p in parts if p.kind != "rbf"]
    if rbfs:
        weight = torch.stack([p.weight for p in rbfs]).sum(0)
        cols = frozenset().union(*(p.cols for p in rbfs))
        head = Leaf("rbf", coef, weight, cols, codes)
    else:
        head = replace(linears.pop(0), coef=coef, codes=codes)
    return replace(head, factors=tuple(linears))


@_closed.register
def _(kernel: DiscreteIntentionKernel, cols: list[int], din: int) -> list[Leaf]:
    _check_unbatched(kernel)
    code = cols[-1]
    return [
        replace(leaf, codes=(*leaf.codes, code))
        for leaf in _leaves(kernel.base_kernel, cols[:-1], din)
    ]
