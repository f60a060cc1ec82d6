"""Kernels of the H-GPDM and the IDDM, built from gpytorch kernels.

Inputs of every transition kernel are the concatenation ``[x, g]`` of a latent state
(``Dx`` columns) and the exogenous variable (``Dg`` columns; for a discrete g one column holding
the integer code). gpytorch's ``RBFKernel``, ``LinearKernel``, ``ScaleKernel``,
``AdditiveKernel`` and ``ProductKernel`` express most terms. This module adds:

- :func:`intention_rbf`: ``exp(-a_x/2 ||x - x'||^2) exp(-a_g/2 ||g - g'||^2)``, one width for
  all latent dims and one for all intention dims (Sec. 2.2.1; the IDDM tensor product of Sec.
  3.2.2 is ``alpha_1`` times this kernel), built as gpytorch's
  ``RBFKernel(active_dims=x) * RBFKernel(active_dims=g)``; the continuous kinds of
  :func:`transition_kernel` use it. It loads the state dicts of :class:`IntentionRBFKernel`,
  the bespoke kernel that earlier releases built (kept so that their pickles still unpickle).
- :class:`DiscreteIntentionKernel`: ``delta(g, g') k(x, x')`` (Sec. 2.2.1, discrete g).

White-noise terms (``beta_2`` in Eq. 1, ``beta_1`` in Eq. 2, ``alpha_4``) act on training points
only, so they are not kernels here: the models add them as GP noise on the training diagonal.

The thesis parameterises widths by inverse squared length scales: ``alpha_2 = 1 / lengthscale^2``.
:func:`measurement_kernel` and :func:`transition_kernel` build the kernels from the thesis's
hyperparameters.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial

import gpytorch
import torch
from gpytorch.constraints import Interval, Positive
from gpytorch.kernels import (
    AdditiveKernel,
    Kernel,
    LinearKernel,
    ProductKernel,
    RBFKernel,
    ScaleKernel,
)
from gpytorch.priors import Prior

from .validation import check_choice

__all__ = [
    "ALPHA_BAR",
    "DenseLinearKernel",
    "DiscreteIntentionKernel",
    "IntentionRBFKernel",
    "MEASUREMENT_KERNELS",
    "TRANSITION_KERNELS",
    "intention_rbf",
    "measurement_kernel",
    "set_requires_grad",
    "transition_kernel",
]

#: Default transition hyperparameters ``[alpha_1, alpha_2, alpha_3, alpha_4]`` (Sec. 2.4.1):
#: RBF signal variance, RBF inverse squared width, linear variance, white noise.
ALPHA_BAR: tuple[float, float, float, float] = (0.9, 0.001, 0.1, 1e-4)

MEASUREMENT_KERNELS = ("rbf", "linear")
TRANSITION_KERNELS = ("gpdm", "continuous", "discrete", "iddm_continuous", "iddm_discrete")


def _part_lengthscale(part: str, kernel: IntentionRBFKernel) -> torch.Tensor:
    """The length scale of ``part`` (x or g) of an :class:`IntentionRBFKernel`: its
    ``lengthscale_{part}`` and its prior's closure."""
    return kernel._get(part)


def _set_part_lengthscale(
    part: str, kernel: IntentionRBFKernel, value: float | torch.Tensor
) -> None:
    """Set the length scale of ``part``: the setter of ``lengthscale_{part}`` and the prior's
    setting closure (``sample_from_prior``)."""
    kernel._set(part, value)


class IntentionRBFKernel(Kernel):
    r"""RBF over ``[x, g]`` with one length scale for the ``x`` dims and one for the ``g`` dims.

    .. math:: k([x, g], [x', g']) = \exp(-\|x - x'\|^2 / (2 l_x^2) - \|g - g'\|^2 / (2 l_g^2))

    so ``alpha_2^x = l_x^{-2}`` and ``alpha_2^g = l_g^{-2}`` in the thesis's notation. Wrap it in a
    ``ScaleKernel`` for the signal variance ``alpha_1``.

    Legacy: earlier releases built the continuous transition kernels with this class; now
    :func:`transition_kernel` builds :func:`intention_rbf`, the same kernel from gpytorch's
    ``RBFKernel`` and ``ProductKernel`` (equal to an ulp, with identical Gaussian-input
    expectations), which loads this kernel's state dicts, so saved model files load into it.
    The class stays so that pickles holding it (models, posteriors, kernels) unpickle and keep
    working, expectations included.

    Args:
        x_dim: number of latent dims ``Dx`` (the first columns of the input).
        g_dim: number of intention dims ``Dg`` (the last columns).
        lengthscale_x_prior: optional gpytorch prior of the latent length scale.
        lengthscale_g_prior: optional gpytorch prior of the intention length scale.
        lengthscale_constraint: constraint of both length scales (default ``Positive()``).

    Shapes: inputs ``[..., N, Dx + Dg]``; output ``[..., N, M]`` (or ``[..., N]`` with diag).
    """

    has_lengthscale = False

    def __init__(
        self,
        x_dim: int,
        g_dim: int,
        lengthscale_x_prior: Prior | None = None,
        lengthscale_g_prior: Prior | None = None,
        lengthscale_constraint: Interval | None = None,
        **kwargs: object,
    ) -> None:
        if x_dim < 1 or g_dim < 1:
            raise ValueError(f"x_dim and g_dim must be >= 1, got {x_dim} and {g_dim}")
        super().__init__(**kwargs)
        self.x_dim, self.g_dim = int(x_dim), int(g_dim)
        constraint = lengthscale_constraint or Positive()
        for part, prior in (("x", lengthscale_x_prior), ("g", lengthscale_g_prior)):
            if prior is not None and not isinstance(prior, Prior):
                raise TypeError(
                    f"lengthscale_{part}_prior must be a gpytorch Prior or None, "
                    f"got {type(prior).__name__}"
                )
            name = f"raw_lengthscale_{part}"
            self.register_parameter(name, torch.nn.Parameter(torch.zeros(*self.batch_shape, 1, 1)))
            self.register_constraint(name, constraint)
            if prior is not None:
                # partials of module-level functions, not lambdas: the kernel stays picklable
                self.register_prior(
                    f"lengthscale_{part}_prior",
                    prior,
                    partial(_part_lengthscale, part),
                    partial(_set_part_lengthscale, part),
                )

    def _get(self, part: str) -> torch.Tensor:
        raw = getattr(self, f"raw_lengthscale_{part}")
        return getattr(self, f"raw_lengthscale_{part}_constraint").transform(raw)

    def _set(self, part: str, value: float | torch.Tensor) -> None:
        raw = getattr(self, f"raw_lengthscale_{part}")
        value = torch.as_tensor(value, dtype=raw.dtype, device=raw.device).expand_as(raw)
        constraint = getattr(self, f"raw_lengthscale_{part}_constraint")
        self.initialize(**{f"raw_lengthscale_{part}": constraint.inverse_transform(value)})

    # the prior's closures are the accessors: one getter and one setter for both parts
    lengthscale_x = property(partial(_part_lengthscale, "x"), partial(_set_part_lengthscale, "x"))
    """Length scale of the latent dims, ``[*batch, 1, 1]`` (settable)."""
    lengthscale_g = property(partial(_part_lengthscale, "g"), partial(_set_part_lengthscale, "g"))
    """Length scale of the intention dims, ``[*batch, 1, 1]`` (settable)."""

    def lengthscale_vector(self) -> torch.Tensor:
        """Per-input-dim length scales ``[*batch, 1, Dx + Dg]`` (the equivalent ARD RBF)."""
        lx = self.lengthscale_x.expand(*self.batch_shape, 1, self.x_dim)
        lg = self.lengthscale_g.expand(*self.batch_shape, 1, self.g_dim)
        return torch.cat([lx, lg], dim=-1)

    def forward(
        self, x1: torch.Tensor, x2: torch.Tensor, diag: bool = False, **params: object
    ) -> torch.Tensor:
        dims = self.x_dim + self.g_dim
        if x1.shape[-1] != dims or x2.shape[-1] != dims:
            raise ValueError(
                f"IntentionRBFKernel expects inputs with {dims} columns ([x, g]), "
                f"got {x1.shape[-1]} and {x2.shape[-1]}"
            )
        ls = self.lengthscale_vector()
        d2 = self.covar_dist(x1 / ls, x2 / ls, diag=diag, square_dist=True)
        return torch.exp(-0.5 * d2)


class DiscreteIntentionKernel(Kernel):
    r"""Block kernel for a discrete intention: ``k([x, g], [x', g']) = delta(g, g') k_x(x, x')``.

    The last input column holds the integer code of g (as a float); ``base_kernel`` sees only the
    preceding ``Dx`` columns. Points of different codes are independent (Sec. 2.2.1).

    Args:
        base_kernel: kernel over the latent state (e.g. ``ScaleKernel(RBFKernel()) +
            LinearKernel()``); it must not set ``active_dims``.
        num_values: number of values K of g; codes are ``0 .. K-1``.
        **kwargs: of gpytorch's ``Kernel`` (``active_dims``, ...). The kernel has no parameters
            of its own: its ``batch_shape`` is the base kernel's (a ``batch_shape`` given here
            must equal it), so that indexing a batch kernel (``kernel[i]``) indexes the base.

    Shapes: inputs ``[..., N, Dx + 1]``; output ``[..., N, M]`` (or ``[..., N]`` with diag).
    """

    has_lengthscale = False

    def __init__(self, base_kernel: Kernel, num_values: int, **kwargs: object) -> None:
        if not isinstance(base_kernel, Kernel):
            raise TypeError(f"base_kernel must be a gpytorch Kernel, got {type(base_kernel)}")
        if int(num_values) < 1:
            raise ValueError(f"num_values must be >= 1, got {num_values}")
        batch_shape = kwargs.pop("batch_shape", None)
        if batch_shape is not None and torch.Size(batch_shape) != base_kernel.batch_shape:
            raise ValueError(
                f"batch_shape {tuple(batch_shape)} differs from the base kernel's "
                f"{tuple(base_kernel.batch_shape)}; give the base kernel the batch shape"
            )
        super().__init__(**kwargs)
        self.base_kernel = base_kernel
        self.num_values = int(num_values)

    @property
    def batch_shape(self) -> torch.Size:
        """The base kernel's batch shape (this kernel has no parameters of its own)."""
        return self.base_kernel.batch_shape

    @batch_shape.setter
    def batch_shape(self, value: torch.Size) -> None:
        # gpytorch's Kernel.__init__ / expand_batch / __getitem__ store a shape here; the base
        # kernel holds the real one, so this copy is never read.
        self._batch_shape = torch.Size(value)

    def forward(
        self, x1: torch.Tensor, x2: torch.Tensor, diag: bool = False, **params: object
    ) -> torch.Tensor:
        # a code outside 0..K-1 would silently match nothing and give the prior
        for x in (x1, x2):
            c = x[..., -1]
            if bool(((c != c.round()) | (c < 0) | (c >= self.num_values)).any()):
                raise ValueError(
                    f"discrete intention codes g must be integers in [0, {self.num_values - 1}]"
                )
        k = self.base_kernel(x1[..., :-1], x2[..., :-1], diag=diag, **params)
        k = k.to_dense() if hasattr(k, "to_dense") else k
        if diag:
            return k * (x1[..., -1] == x2[..., -1]).to(k.dtype)
        same = x1[..., :, -1:] == x2[..., :, -1:].transpose(-1, -2)
        return k * same.to(k.dtype)


class DenseLinearKernel(LinearKernel):
    """gpytorch's ``LinearKernel`` returning a dense tensor.

    gpytorch returns a low-rank operator for ``k(X, X)``; adding it to the dense RBF term of a sum
    kernel makes linear_operator take a jittered Cholesky of that term (slow, and it warns).
    The GP code here factorises dense matrices itself, so this subclass returns
    ``variance * x1 x2^T`` densely. Shapes: ``[..., N, D], [..., M, D] -> [..., N, M]``.
    """

    def forward(
        self, x1: torch.Tensor, x2: torch.Tensor, diag: bool = False, **params: object
    ) -> torch.Tensor:
        v = self.variance  # [*batch, 1, D or 1]
        if diag:
            return (x1 * x2 * v).sum(-1)
        return (x1 * v) @ x2.transpose(-1, -2)


def intention_rbf(
    x_dim: int, g_dim: int, lengthscale_x: float = 1.0, lengthscale_g: float = 1.0
) -> ProductKernel:
    r"""The continuous-g RBF ``RBF(x) * RBF(g)`` over ``[x, g]`` inputs, as gpytorch kernels.

    .. math:: k([x, g], [x', g']) = \exp(-\|x - x'\|^2 / (2 l_x^2))
              \exp(-\|g - g'\|^2 / (2 l_g^2))

    ``kernels[0]`` is an isotropic ``RBFKernel`` on the first ``x_dim`` columns, ``kernels[1]``
    one on the last ``g_dim`` columns (``alpha_2^x = l_x^{-2}``, ``alpha_2^g = l_g^{-2}``). The
    parameters have the shapes of :class:`IntentionRBFKernel`'s, and a state dict of that kernel
    (``raw_lengthscale_x``, ``raw_lengthscale_g`` and their constraints' buffers) loads into
    this one (a load-state-dict pre-hook renames them), giving the same kernel to an ulp.

    Shapes: inputs ``[..., N, x_dim + g_dim]``; output ``[..., N, M]``.
    """
    if x_dim < 1 or g_dim < 1:
        raise ValueError(f"x_dim and g_dim must be >= 1, got {x_dim} and {g_dim}")
    rbf_x = RBFKernel(active_dims=torch.arange(x_dim))
    rbf_g = RBFKernel(active_dims=torch.arange(x_dim, x_dim + g_dim))
    rbf_x.lengthscale, rbf_g.lengthscale = lengthscale_x, lengthscale_g
    kernel = ProductKernel(rbf_x, rbf_g)
    kernel.register_load_state_dict_pre_hook(_load_intention_rbf_state)
    return kernel


def _load_intention_rbf_state(
    module: ProductKernel, state_dict: dict[str, torch.Tensor], prefix: str, *args: object
) -> None:
    """Load-state-dict pre-hook of :func:`intention_rbf`: rename the entries of an
    :class:`IntentionRBFKernel` state dict (length scale ``x`` -> factor 0, ``g`` -> factor 1)
    and add the factors' ``active_dims`` buffers, which that kernel did not have."""
    if f"{prefix}raw_lengthscale_x" not in state_dict:
        return
    for part, index in (("x", 0), ("g", 1)):
        for suffix in ("", "_constraint.lower_bound", "_constraint.upper_bound"):
            old = f"{prefix}raw_lengthscale_{part}{suffix}"
            if old in state_dict:
                state_dict[f"{prefix}kernels.{index}.raw_lengthscale{suffix}"] = state_dict.pop(old)
        state_dict.setdefault(
            f"{prefix}kernels.{index}.active_dims", module.kernels[index].active_dims
        )


def _rbf_lengthscale(inverse_width: float) -> float:
    if not inverse_width > 0:
        raise ValueError(f"RBF inverse squared width must be positive, got {inverse_width}")
    return float(inverse_width) ** -0.5


def measurement_kernel(kind: str | Kernel, beta1: float = 1.0) -> Kernel:
    """Measurement kernel ``k_z`` without its noise term.

    Args:
        kind: ``"rbf"`` for Eq. 1 (isotropic RBF, unit signal variance, inverse squared width
            ``beta1``) or ``"linear"`` for Eq. 2 (``x^T x'``, variance fixed to 1 because the
            output scales W carry the signal variance); or a gpytorch ``Kernel`` over latent
            states, returned as it is (its own priors and constraints apply).
        beta1: initial inverse squared width for ``"rbf"``; ignored otherwise.

    Returns:
        A gpytorch kernel over latent states ``[..., N, Dx]``.

    Raises:
        TypeError: ``kind`` is neither a str nor a gpytorch Kernel.
        ValueError: ``kind`` is an unknown name.
    """
    if isinstance(kind, Kernel):
        return kind
    if not isinstance(kind, str):
        raise TypeError(
            f"measurement kernel must be one of {MEASUREMENT_KERNELS} or a gpytorch Kernel, "
            f"got {type(kind).__name__}"
        )
    check_choice(kind, "measurement kernel", MEASUREMENT_KERNELS)
    if kind == "rbf":
        k = RBFKernel()
        k.lengthscale = _rbf_lengthscale(beta1)
        return k
    k = DenseLinearKernel()
    k.variance = 1.0
    k.raw_variance.requires_grad_(False)
    return k


def transition_kernel(
    kind: str,
    x_dim: int,
    *,
    g_dim: int = 1,
    num_values: int | None = None,
    alpha: Sequence[float] = ALPHA_BAR,
    alpha_g: Sequence[float] = (1.0, 0.1),
    sharing: float = 0.0,
    phase_width: float | None = None,
) -> Kernel:
    """Transition kernel ``k_x`` without its white-noise term ``alpha_4``.

    Args:
        kind: one of :data:`TRANSITION_KERNELS`:

            - ``"gpdm"``: ``alpha_1 RBF(x) + alpha_3 x^T x'`` (no g; inputs ``[N, Dx]``);
            - ``"continuous"``: ``alpha_1 exp(-alpha_2/2 |x-x'|^2 - alpha_2^g/2 |g-g'|^2)
              + alpha_3 x^T x' + alpha_3^g g^T g'`` (Sec. 2.2.1);
            - ``"discrete"``: ``delta(g, g') [alpha_1 RBF(x) + alpha_3 x^T x']`` (Sec. 2.2.1);
            - ``"iddm_continuous"``: ``alpha_1 exp(-alpha_2/2 |x-x'|^2 - alpha_2^g/2 |g-g'|^2)``
              (tensor product, Sec. 3.2.2);
            - ``"iddm_discrete"``: ``delta(g, g') alpha_1 RBF(x)`` (Sec. 3.2.2 with
              ``alpha_3 = inf``).

            The RBF of the continuous kinds is :func:`intention_rbf`,
            ``ScaleKernel(RBF(x) * RBF(g))``; their state dicts from earlier releases (with
            :class:`IntentionRBFKernel` there) load into it.
        x_dim: latent dimension ``Dx``.
        g_dim: intention dimension ``Dg`` for continuous g (discrete g uses one code column).
        num_values: number of values K of a discrete g (required for the discrete kinds).
        alpha: ``[alpha_1, alpha_2, alpha_3, alpha_4]``; ``alpha_4`` is the noise and is not used
            here.
        alpha_g: ``[alpha_2^g, alpha_3^g]`` for continuous g: inverse squared width and linear
            variance of the intention dims.
        sharing: for the discrete kinds, the share ``rho`` in ``[0, 1)`` of the dynamics common to
            all values of g: ``k = rho k_0(x, x') + (1 - rho) delta(g, g') k_0(x, x')`` with
            ``k_0`` the kind's base kernel (an intrinsic coregionalisation model whose
            correlation between different values of g is ``rho``; not in the thesis). ``0``, the
            default, is the thesis's block kernel. Each part has its own hyperparameters, so a
            fit with learned alpha can move them apart.
        phase_width: for the IDDM kinds, the width ``w`` (in frames) of a phase factor: the
            kernel is multiplied by ``exp(-(p - p')^2 / (2 w^2))`` over one more input column,
            the phase ``p`` (the frame index of ``x_t`` from its sequence's start), so that the
            dynamics may change along a stroke, as the per-frame transitions of
            :class:`~hgpdm_torch.models.LinearIDDM` do (not in the thesis). ``None`` (default):
            no phase column.

    Returns:
        A gpytorch kernel over ``[..., N, Dx + Dg]`` inputs (``[..., N, Dx]`` for ``"gpdm"``),
        ``[..., N, Dx + Dg + 1]`` with a phase: ``[x, g, p]``.
    """
    check_choice(kind, "transition kernel", TRANSITION_KERNELS)
    if len(alpha) != 4:
        raise ValueError(f"alpha must have 4 entries [a1, a2, a3, a4], got {len(alpha)}")
    a1, a2, a3, _ = (float(a) for a in alpha)
    if len(alpha_g) != 2:
        raise ValueError(f"alpha_g must have 2 entries [a2_g, a3_g], got {len(alpha_g)}")
    if not all(v > 0 for v in (a1, a2, a3, *map(float, alpha_g))):
        raise ValueError(
            f"alpha and alpha_g must be positive, got alpha={alpha}, alpha_g={alpha_g}"
        )
    if kind in ("discrete", "iddm_discrete") and (num_values is None or num_values < 1):
        raise ValueError(f"num_values must be a positive int for kind={kind!r}")
    if not 0.0 <= float(sharing) < 1.0:
        raise ValueError(f"sharing must lie in [0, 1), got {sharing!r}")
    if sharing and kind not in ("discrete", "iddm_discrete"):
        raise ValueError(f"sharing applies to the discrete kinds only, got kind={kind!r}")
    if phase_width is not None:
        if kind not in ("iddm_continuous", "iddm_discrete"):
            raise ValueError(f"phase_width applies to the IDDM kinds only, got kind={kind!r}")
        if isinstance(phase_width, bool) or not (
            isinstance(phase_width, int | float) and 0 < phase_width < float("inf")
        ):
            raise ValueError(
                f"phase_width must be a positive number of frames, got {phase_width!r}"
            )
        base = transition_kernel(
            kind, x_dim, g_dim=g_dim, num_values=num_values, alpha=alpha, alpha_g=alpha_g,
            sharing=sharing,
        )  # fmt: skip
        g_cols = 1 if kind == "iddm_discrete" else g_dim
        # the base sees [x, g] (a discrete code must be its last column), the factor p
        base.active_dims = torch.arange(x_dim + g_cols)
        phase = RBFKernel(active_dims=torch.tensor([x_dim + g_cols]))
        phase.lengthscale = float(phase_width)
        return ProductKernel(base, phase)

    def scaled(base: Kernel, share: float = 1.0, active: Sequence[int] | None = None) -> Kernel:
        k = ScaleKernel(base, active_dims=None if active is None else torch.as_tensor(list(active)))
        k.outputscale = a1 * share
        return k

    def linear(active: Sequence[int] | None, variance: float) -> LinearKernel:
        k = DenseLinearKernel(active_dims=None if active is None else torch.as_tensor(list(active)))
        k.variance = variance
        return k

    def rbf_x() -> RBFKernel:
        k = RBFKernel()
        k.lengthscale = _rbf_lengthscale(a2)
        return k

    if kind == "gpdm":
        return AdditiveKernel(scaled(rbf_x()), linear(None, a3))
    if kind in ("discrete", "iddm_discrete"):
        rho, cols = float(sharing), range(x_dim)

        def base(share: float, active: Sequence[int] | None) -> Kernel:
            rbf = scaled(rbf_x(), share, active)
            if kind == "iddm_discrete":
                return rbf
            return AdditiveKernel(rbf, linear(active, a3 * share))

        style = DiscreteIntentionKernel(base(1.0 - rho, None), num_values)
        return style if rho == 0.0 else AdditiveKernel(base(rho, cols), style)
    if g_dim < 1:
        raise ValueError(f"g_dim must be >= 1, got {g_dim}")
    rbf = intention_rbf(x_dim, g_dim, _rbf_lengthscale(a2), _rbf_lengthscale(float(alpha_g[0])))
    if kind == "iddm_continuous":
        return scaled(rbf)
    x_cols, g_cols = range(x_dim), range(x_dim, x_dim + g_dim)
    return AdditiveKernel(scaled(rbf), linear(x_cols, a3), linear(g_cols, float(alpha_g[1])))


def set_requires_grad(kernel: gpytorch.Module, flag: bool) -> None:
    """Freeze (``False``) or free (``True``) every raw hyperparameter of a kernel."""
    for p in kernel.parameters():
        p.requires_grad_(flag)
