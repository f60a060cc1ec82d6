"""Input validation for the public API: one place for the shape, dtype and finiteness checks.

Every public function that takes user data calls these helpers so that bad input produces a
``TypeError`` or ``ValueError`` that names the argument and what was expected.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence

import numpy as np
import torch

__all__ = [
    "check_sequences",
    "as_observations",
    "as_tensor",
    "bad_observation",
    "check_choice",
    "check_dtype",
    "check_finite",
    "check_magnitude",
    "check_outlier_sd",
    "check_probability",
    "check_shape",
    "positive_reals",
    "real_scalar",
]


def as_tensor(
    value: object,
    name: str,
    *,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
    ndim: int | None = None,
    min_ndim: int | None = None,
    allow_nan: bool = False,
) -> torch.Tensor:
    """Convert array-like input to a floating tensor and validate it.

    Args:
        value: tensor, NumPy array or nested sequence of numbers.
        name: the argument's name, used in error messages.
        dtype: floating dtype to convert to; ``None`` keeps a floating tensor's dtype and turns
            anything else into float64.
        device: device to move to (default: keep).
        ndim: exact number of dimensions required.
        min_ndim: minimum number of dimensions required.
        allow_nan: whether NaN entries are allowed (e.g. to mark missing observations);
            inf is never allowed.

    Returns:
        The validated tensor.
    """
    if isinstance(value, torch.Tensor):
        t = value
    elif isinstance(value, np.ndarray | Sequence | float | int):
        try:
            # on the CPU, as NumPy data is, whatever torch's default device
            t = torch.as_tensor(np.asarray(value, dtype=np.float64), device="cpu")
        except (TypeError, ValueError) as err:
            raise TypeError(
                f"{name} must be numeric array-like, got {type(value).__name__}"
            ) from err
    else:
        raise TypeError(f"{name} must be a tensor or array-like, got {type(value).__name__}")
    if t.dtype == torch.bool or not (t.is_floating_point() or t.dtype in _INT_DTYPES):
        raise TypeError(f"{name} must have a real numeric dtype, got {t.dtype}")
    if dtype is not None:
        t = t.to(dtype)
    elif not t.is_floating_point():
        t = t.to(torch.float64)
    if device is not None:
        t = t.to(device)
    if ndim is not None and t.dim() != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {tuple(t.shape)}")
    if min_ndim is not None and t.dim() < min_ndim:
        raise ValueError(
            f"{name} must have at least {min_ndim} dimensions, got shape {tuple(t.shape)}"
        )
    check_finite(t, name, allow_nan=allow_nan)
    return t


_INT_DTYPES = (torch.int8, torch.int16, torch.int32, torch.int64, torch.uint8)


def check_finite(t: torch.Tensor, name: str, *, allow_nan: bool = False) -> None:
    """Raise ``ValueError`` if ``t`` holds inf (or NaN, unless ``allow_nan``).

    Without NaN allowed, a finite sum of ``t`` settles it in one reduction (NaN or inf in any
    entry makes every summation order NaN or inf); only a sum that is not finite (a bad entry,
    or finite entries that overflow it) is looked at entry by entry.
    """
    if allow_nan:
        if bool(torch.isinf(t).any()):
            raise ValueError(f"{name} contains inf; expected finite values (NaN marks missing)")
    elif not math.isfinite(float(t.detach().sum())) and not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} contains NaN or inf; expected finite values")


def check_shape(t: torch.Tensor, name: str, shape: Sequence[int | None]) -> None:
    """Check the trailing dims of ``t`` against ``shape`` (``None`` matches any size)."""
    if t.dim() < len(shape) or any(
        s is not None and s != d
        for s, d in zip(shape, t.shape[t.dim() - len(shape) :], strict=True)
    ):
        want = ", ".join("*" if s is None else str(s) for s in shape)
        raise ValueError(f"{name} must have trailing shape [{want}], got {tuple(t.shape)}")


def check_probability(p: torch.Tensor, name: str, *, atol: float = 1e-6) -> None:
    """Check that the last dim of ``p`` holds probability vectors (non-negative, sum to 1)."""
    check_finite(p, name)
    if p.numel() == 0:
        raise ValueError(f"{name} must not be empty")
    if bool((p < -atol).any()) or not torch.allclose(
        p.sum(-1), torch.ones((), dtype=p.dtype, device=p.device), atol=atol
    ):
        raise ValueError(f"{name} must be non-negative and sum to 1 along its last dim")


def check_choice(value: str, name: str, choices: Sequence[str]) -> str:
    """Check that ``value`` is one of ``choices`` and return it."""
    if not isinstance(value, str) or value not in choices:
        raise ValueError(
            f"unknown {name} {value!r}; expected one of {', '.join(map(repr, choices))}"
        )
    return value


def real_scalar(value: object, name: str) -> float:
    """``value`` as a float: a Python or NumPy real number or a 0-dim real tensor (not a bool).

    Raises:
        TypeError: anything else, naming ``name``.
    """
    if isinstance(value, torch.Tensor):
        if value.dim() != 0 or value.dtype == torch.bool or value.is_complex():
            raise TypeError(
                f"{name} must be a real number or a 0-dim real tensor, got a tensor of shape "
                f"{tuple(value.shape)} and dtype {value.dtype}"
            )
        return float(value)
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {type(value).__name__}")
    return float(value)


def positive_reals(value: object, name: str, size: int) -> tuple[float, ...]:
    """``value`` as ``size`` positive finite floats: a sequence, array or 1-D tensor of reals.

    Raises:
        TypeError: not a sequence of real numbers (a lone number, a str, a bool entry).
        ValueError: not ``size`` entries, or an entry that is not positive and finite.
    """
    what = f"a sequence of {size} positive finite numbers"
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().reshape(-1).tolist() if value.dim() == 1 else value
    elif isinstance(value, np.ndarray) and value.ndim == 1:
        value = value.tolist()
    if not isinstance(value, Sequence) or isinstance(value, str | bytes):
        raise TypeError(f"{name} must be {what}, got {value!r}")
    entries = []
    for i, v in enumerate(value):
        try:
            entries.append(real_scalar(v, f"{name}[{i}]"))
        except TypeError as err:
            raise TypeError(f"{name} must be {what}: {err}") from None
    if len(entries) != size:
        raise ValueError(f"{name} must be {what}, got {len(entries)}: {list(value)!r}")
    bad = [v for v in entries if not (v > 0 and math.isfinite(v))]
    if bad:
        raise ValueError(f"{name} must be {what}, got {list(value)!r}")
    return tuple(entries)


#: The floating dtypes of the models (GP algebra needs at least float32; float16 and bfloat16
#: have no Cholesky factor on the CPU and far too little precision).
MODEL_DTYPES = (torch.float32, torch.float64)


def check_dtype(dtype: object, name: str = "dtype") -> torch.dtype:
    """``dtype`` if it is one of :data:`MODEL_DTYPES`.

    A string such as ``"float64"`` is refused, as torch itself does, with a hint: accepting it
    here only would make ``dtype`` mean different things in different calls.

    Raises:
        TypeError: anything else, naming ``name`` and the accepted values.
    """
    if isinstance(dtype, torch.dtype) and dtype in MODEL_DTYPES:
        return dtype
    hint = f" (a str; pass torch.{dtype} instead)" if isinstance(dtype, str) else ""
    raise TypeError(f"{name} must be torch.float32 or torch.float64, got {dtype!r}{hint}")


def check_magnitude(t: torch.Tensor, name: str) -> None:
    """Refuse data whose magnitude the model's arithmetic in ``t.dtype`` cannot carry.

    A GP model squares its data (channel variances, output scales ``1 / std``, predictive
    variances ``std^2``): the largest magnitude must lie between ``sqrt(finfo.tiny) 1e4`` and
    ``sqrt(finfo.max) 1e-4`` (about 1e-150 and 1e150 in float64, 1e-15 and 1e15 in float32),
    so that a sum of squares over up to 1e8 frames neither overflows nor underflows. Zero data
    are left to the caller's checks (a constant channel).

    Raises:
        ValueError: naming ``name``, the largest magnitude found, the bound and what to do.
    """
    if t.numel() == 0:
        return
    info = torch.finfo(t.dtype)
    high, low = math.sqrt(info.max) * 1e-4, math.sqrt(info.tiny) * 1e4
    biggest = float(t.detach().abs().max())
    if biggest > high or 0 < biggest < low:
        where = f"above {high:.1e}" if biggest > high else f"below {low:.1e}"
        raise ValueError(
            f"{name} hold values up to {biggest:.3g} in magnitude, {where}, where the model's "
            f"{str(t.dtype).removeprefix('torch.')} arithmetic (squares for variances and "
            "output scales) overflows or underflows; rescale the data, e.g. standardise each "
            "channel (hgpdm_torch.datasets.Standardizer) or change its units"
        )


def check_outlier_sd(outlier_sd: object) -> float | None:
    """The outlier threshold of the observation checks, in training standard deviations: a
    positive float, or ``None`` (no threshold)."""
    if outlier_sd is None:
        return None
    value = real_scalar(outlier_sd, "outlier_sd")
    if not value > 0:
        raise ValueError(f"outlier_sd must be positive (or None to disable), got {outlier_sd!r}")
    return value


def as_observations(z: object, min_ndim: int) -> torch.Tensor:
    """``z`` as a real floating tensor (integers become float64), NaN and inf kept so that
    :class:`ObservationCheck` can say which row is bad."""
    if not isinstance(z, torch.Tensor):
        try:
            z = torch.as_tensor(np.asarray(z, dtype=np.float64))
        except (TypeError, ValueError) as err:
            raise TypeError(
                f"z must be a tensor or numeric array-like, got {type(z).__name__}"
            ) from err
    if z.dtype == torch.bool or z.is_complex():
        raise TypeError(f"z must have a real numeric dtype, got {z.dtype}")
    if not z.is_floating_point():
        z = z.to(torch.float64)
    if z.dim() < min_ndim:
        raise ValueError(f"z must have at least {min_ndim} dimensions, got shape {tuple(z.shape)}")
    return z


def bad_observation(where: str, why: str) -> ValueError:
    """The error for an observation row that cannot be used: ``where`` names it (batch index,
    step, stream), ``why`` says what is wrong with it."""
    return ValueError(f"{where} cannot be used: {why}")


def check_sequences(sequences: object, dtype: torch.dtype) -> list[torch.Tensor]:
    """Training sequences as a list of finite ``[T_j, Dz]`` tensors of ``dtype``, on the first
    one's device: a list of J >= 1 arrays (lengths may differ, each with ``T_j >= 2`` frames, a
    transition) or a ``[J, T, Dz]`` tensor or array.

    Raises:
        TypeError: not a list, tensor or array.
        ValueError: no sequence, a wrong shape, fewer than 2 frames, no or differing observed
            dims, or a value that is not finite; the message names the sequence.
    """
    if isinstance(sequences, np.ndarray) and sequences.dtype != object:
        sequences = torch.as_tensor(sequences)
    if isinstance(sequences, torch.Tensor):
        if sequences.dim() != 3:
            raise ValueError(
                f"sequences as a tensor must have shape [J, T, Dz], got {tuple(sequences.shape)}"
            )
        sequences = list(sequences)
    if not isinstance(sequences, Sequence) or isinstance(sequences, str):
        raise TypeError(
            f"sequences must be a list of [T, Dz] arrays, got {type(sequences).__name__}"
        )
    if len(sequences) == 0:
        raise ValueError("sequences must contain at least one sequence, got an empty list")
    out: list[torch.Tensor] = []
    for j, s in enumerate(sequences):
        t = as_tensor(s, f"sequences[{j}]", ndim=2, dtype=dtype)
        if t.shape[0] < 2:
            raise ValueError(
                f"sequences[{j}] must have at least 2 frames (a transition), got {t.shape[0]}"
            )
        if t.shape[1] < 1:
            raise ValueError(f"sequences[{j}] must have at least one observed dim")
        if out and t.shape[1] != out[0].shape[1]:
            raise ValueError(
                f"sequences[{j}] has {t.shape[1]} observed dims, expected {out[0].shape[1]} "
                "like sequences[0]"
            )
        out.append(t.to(out[0].device) if out else t)
    return out
