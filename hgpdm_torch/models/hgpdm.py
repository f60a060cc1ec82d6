"""The Hierarchical GPDM (H-GPDM, thesis Sec. 2.2) and the Intention-Driven Dynamics Model (IDDM,
Sec. 3.2), and the unsupervised discovery of a discrete exogenous variable (Algorithm 2.1).

The exogenous variable g (a style, an intention, a target) is constant within a sequence and
enters the transition GP as extra input columns: ``f([x_t, g]) -> x_{t+1}``. A discrete g is coded
``0 .. K-1`` in one column; a continuous g has ``Dg`` columns.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from gpytorch.kernels import Kernel
from scipy.optimize import minimize_scalar
from sklearn.cluster import KMeans

from ..fitting import FitResult
from ..gp import GPPosterior
from ..kernels import DiscreteIntentionKernel, transition_kernel
from ..linalg import gaussian_nll
from ..progress import trange
from ..validation import as_tensor, check_choice, check_dtype, check_sequences, positive_reals
from .gpdm import GPDM, NOISE_FLOOR, SequencesLike

__all__ = ["HGPDM", "IDDM", "trajectory_summaries"]

INTENTION_KINDS = ("discrete", "continuous")


def _check_intentions(
    intentions: Any, num_sequences: int, kind: str, num_values: int | None, dtype: torch.dtype
) -> tuple[torch.Tensor, int | None]:
    """Validate g per sequence; returns ``[J, Dg]`` values (codes for discrete) and K."""
    if kind == "discrete":
        try:  # a tensor as it is (on any device); anything else through NumPy, on the CPU
            g = (
                intentions.detach().cpu()
                if isinstance(intentions, torch.Tensor)
                else torch.as_tensor(np.asarray(intentions), device="cpu")
            )
        except (TypeError, ValueError, RuntimeError) as err:
            raise TypeError(f"intentions must be a [J] vector of ints, got {intentions!r}") from err
        if not (
            g.is_floating_point()
            or g.dtype in (torch.int8, torch.int16, torch.int32, torch.int64, torch.uint8)
        ):
            raise TypeError(f"discrete intentions must be integers, got {g.dtype}")
        if g.dim() != 1 or g.is_floating_point() and not bool((g == g.round()).all()):
            raise ValueError(
                f"discrete intentions must be a [J] vector of ints, got {tuple(g.shape)}"
            )
        if g.is_complex() or g.dtype == torch.bool:
            raise TypeError(f"discrete intentions must be integers, got dtype {g.dtype}")
        g = g.long()
        if g.numel() == 0:
            raise ValueError("discrete intentions must not be empty: one code per sequence")
        k = int(g.max()) + 1 if num_values is None else int(num_values)
        if k < 1:
            raise ValueError(f"num_values must be >= 1, got {k}")
        if bool((g < 0).any()) or bool((g >= k).any()):
            raise ValueError(f"discrete intentions must lie in [0, {k - 1}], got {g.tolist()}")
        used = torch.unique(g)
        if num_values is None and 2 * used.numel() < k:
            # Every code 0..K-1 is a value of g that inference scores; labels such as
            # subject numbers would make most of them values without a training sequence.
            shown = ", ".join(map(str, used[:8].tolist())) + (", ..." if len(used) > 8 else "")
            raise ValueError(
                f"discrete intentions are codes 0..K-1, K = max + 1 = {k} here, but only "
                f"{used.numel()} of them are used ([{shown}]); recode the labels to "
                f"0..{used.numel() - 1} (e.g. numpy.unique(labels, return_inverse=True)[1]) "
                f"or pass num_values={k} to keep the unused codes"
            )
        values = g.to(dtype).unsqueeze(-1)
    else:
        values = as_tensor(intentions, "intentions", dtype=dtype)
        if values.dim() == 1:
            values = values.unsqueeze(-1)
        if values.dim() != 2:
            raise ValueError(
                f"continuous intentions must be [J] or [J, Dg], got {tuple(values.shape)}"
            )
        k = None
    if values.shape[0] != num_sequences:
        raise ValueError(
            f"got {values.shape[0]} intentions for {num_sequences} sequences; need one per sequence"
        )
    return values, k


def trajectory_summaries(latents: Sequence[torch.Tensor]) -> np.ndarray:
    """Per-sequence summaries of latent trajectories ``[T_j, Dx]``: the mean position and the
    root-mean-square step per latent dim, ``[J, 2 Dx]`` (the k-means features that start
    :meth:`HGPDM.discover`, and the k-means baseline of style discovery)."""
    feats = []
    for lat in latents:
        step = lat[1:] - lat[:-1]
        feats.append(torch.cat([lat.mean(0), step.pow(2).mean(0).sqrt()]).cpu().numpy())
    return np.stack(feats)


#: A continuous g whose spread (in a dimension) is below this share of the g kernel's width
#: ``1 / sqrt(alpha_g[0])`` warns: every training g then looks alike to the transition kernel
#: (``exp(-alpha_g[0] (g - g')^2 / 2) > 0.99`` for g one spread apart) and the beliefs over g
#: stay near uniform (with g scaled by 0.01, sd 0.0066, the belief sources' GP IDDM gave a
#: belief whose spread was 1.1 of g's: uniform; at unit scale 0.06).
NARROW_INTENTION_SHARE = 0.1


def _warn_narrow_intentions(values: torch.Tensor, inverse_width2: float) -> None:
    """Warn where a continuous g's standard deviation ``[J, Dg]`` is below
    :data:`NARROW_INTENTION_SHARE` of the kernel's g width (a constant dim is left alone)."""
    if values.shape[0] < 2:
        return
    width = 1.0 / math.sqrt(inverse_width2)
    for d, sd in enumerate(values.std(0).tolist()):
        if 0 < sd < NARROW_INTENTION_SHARE * width:
            dim = f" (dim {d})" if values.shape[1] > 1 else ""
            warnings.warn(
                f"the intentions{dim} have a standard deviation of {sd:.3g}, below "
                f"{NARROW_INTENTION_SHARE} of the transition kernel's g width 1 / sqrt(alpha_g[0])"
                f" = {width:.3g}: every g looks alike to the dynamics and the beliefs over g stay "
                "near uniform; standardise g (subtract its mean, divide by its standard "
                "deviation) and map the belief's values back, or pass a larger alpha_g[0]",
                stacklevel=3,
            )


class HGPDM(GPDM):
    """Hierarchical GPDM: GP dynamics driven by an exogenous variable g (Sec. 2.2.1).

    Args:
        sequences: J sequences ``[T_j, Dz]`` (see :class:`GPDM`).
        intentions: g per sequence: ``[J]`` integer codes in ``0 .. K-1`` (``intention=
            "discrete"``) or ``[J]`` / ``[J, Dg]`` reals (``intention="continuous"``).
        latent_dim: ``Dx``.
        intention: ``"discrete"`` or ``"continuous"``.
        num_values: K for a discrete g (default ``max(intentions) + 1``). Every code
            ``0 .. K-1`` is a value of g that inference scores, also one without a training
            sequence; codes that leave more than half of ``0 .. max`` unused (labels such as
            subject numbers) are refused unless ``num_values`` is given.
        alpha_g: ``[alpha_2^g, alpha_3^g]`` of the continuous kernel (inverse squared width and
            linear variance of g), two positive finite numbers.
        sharing: for a discrete g, the share ``rho`` in ``[0, 1)`` of the transition kernel common
            to all values of g: ``rho k(x, x') + (1 - rho) delta(g, g') k(x, x')`` (see
            :func:`~hgpdm_torch.kernels.transition_kernel`). ``0`` (default) is the thesis's
            independent dynamics per value; ``rho > 0`` lets values with few training sequences
            borrow the shape of the dynamics from the others (not in the thesis).
        noise_per_value: give each value k of a discrete g (with ``sharing = 0``: independent
            dynamics per value) its own process noise ``alpha_4,k`` (:attr:`value_noise`, a
            ``[K]`` buffer saved with the model) instead of the shared ``alpha_4`` (not in the
            thesis). The MAP fit runs with the current ``alpha_4,k`` (initially all
            ``alpha[3]``); at its end :meth:`fit` calls :meth:`estimate_value_noise`, which sets
            each ``alpha_4,k`` to the maximum-likelihood noise of value k's transitions with the
            latents and the kernel fixed. Values whose recordings differ in loudness (standing vs
            running) then no longer share one process noise, which otherwise biases the
            transition evidence towards the loud values. Not with ``learn_noise``/``learn_alpha``.
        **kwargs: see :class:`GPDM` (``measurement``, ``alpha``, ``priors``, ``learn_alpha``,
            ``init``, ``dtype``).

    Raises:
        TypeError: intentions that are not numbers (or not integers for a discrete g), or
            a bad type of another argument (see :class:`GPDM`).
        ValueError: not one intention per sequence; discrete codes that are negative, at or
            above ``num_values``, or sparse (see ``num_values``); ``alpha_g`` not two positive
            finite numbers; or another argument out of range (see :class:`GPDM`).

    The transition kernel is ``delta(g, g') [alpha_1 RBF(x) + alpha_3 x^T x']`` for a discrete g and
    ``alpha_1 RBF([x, g]) + alpha_3 x^T x' + alpha_3^g g g'`` for a continuous g (Sec. 2.2.1);
    with ``sharing = rho`` the discrete kernel is
    ``rho k(x, x') + (1 - rho) delta(g, g') k(x, x')``.
    """

    kinds = {"discrete": "discrete", "continuous": "continuous"}
    #: width of a phase factor of the transition kernel (:class:`IDDM` only; ``None``: none)
    phase_width: float | None = None
    #: whether each value of a discrete g has its own process noise (class default: models
    #: pickled before the option existed have none)
    noise_per_value = False

    def __init__(
        self,
        sequences: SequencesLike,
        intentions: Any,
        latent_dim: int = 3,
        *,
        intention: str = "discrete",
        num_values: int | None = None,
        alpha_g: Sequence[float] = (1.0, 0.1),
        sharing: float = 0.0,
        noise_per_value: bool = False,
        **kwargs: Any,
    ) -> None:
        check_choice(intention, "intention", INTENTION_KINDS)
        if not isinstance(noise_per_value, bool | np.bool_):
            raise TypeError(f"noise_per_value must be a bool, got {noise_per_value!r}")
        if noise_per_value and (
            intention != "discrete"
            or sharing
            or kwargs.get("learn_noise")
            or kwargs.get("learn_alpha")
        ):
            raise ValueError(
                "noise_per_value=True needs a discrete intention with sharing=0 (independent "
                "dynamics per value) and a fixed process noise (no learn_noise/learn_alpha); got "
                f"intention={intention!r}, sharing={sharing!r}"
            )
        if isinstance(sharing, bool) or not isinstance(sharing, int | float):
            raise TypeError(f"sharing must be a float in [0, 1), got {sharing!r}")
        if not 0.0 <= float(sharing) < 1.0:
            raise ValueError(f"sharing must lie in [0, 1), got {sharing!r}")
        if sharing and intention != "discrete":
            raise ValueError("sharing applies to a discrete intention only")
        self.sharing = float(sharing)
        dtype = check_dtype(kwargs.get("dtype", torch.float64))
        alpha_g = positive_reals(alpha_g, "alpha_g", 2)
        num_seq = len(check_sequences(sequences, dtype))
        values, k = _check_intentions(intentions, num_seq, intention, num_values, dtype)
        self.intention = intention
        self.num_values = k
        self.intention_dim = values.shape[1]
        self.alpha_g = alpha_g
        if intention == "continuous":
            _warn_narrow_intentions(values, alpha_g[0])
        super().__init__(sequences, latent_dim, **kwargs)
        self.register_buffer("intentions", values.to(self.observations.device))
        self._config.update(
            intention=intention, num_values=k, alpha_g=list(self.alpha_g), sharing=self.sharing
        )
        self.noise_per_value = bool(noise_per_value)
        if self.noise_per_value:
            self._config["noise_per_value"] = True
            self.register_buffer("value_noise", self.transition_noise.detach().expand(k).clone())

    @property
    def transition_kind(self) -> str:  # type: ignore[override]
        return self.kinds[self.intention]

    def build_transition_kernel(self) -> Kernel:
        return transition_kernel(
            self.transition_kind,
            self.latent_dim,
            g_dim=self.intention_dim,
            num_values=self.num_values,
            alpha=self.alpha_init,
            alpha_g=self.alpha_g,
            sharing=self.sharing,
            phase_width=self.phase_width,
        )

    def transition_inputs(self, latent: torch.Tensor) -> torch.Tensor:
        """``[m, Dx + Dg]`` inputs ``[x_t, g]`` of the transition GP."""
        return torch.cat([latent[self.src_index], self.intentions[self.seq_of_src]], dim=-1)

    def transition_blocks(self) -> list[torch.Tensor]:
        """One block of ``K_x`` per value of a discrete g (``delta(g, g')`` zeroes the rest)."""
        if (
            self.intention != "discrete"
            or self.sharing
            or ("transition_kernel" in getattr(self, "_object_arguments", ())
                and not isinstance(self.transition_kernel, DiscreteIntentionKernel))
        ):  # fmt: skip
            return super().transition_blocks()
        codes = self.intentions[self.seq_of_src, 0]
        return [
            rows
            for k in range(self.num_values)
            if (rows := torch.nonzero(codes == k)[:, 0]).numel()
        ]

    def transition_block_noise(self, rows: torch.Tensor) -> torch.Tensor:
        """alpha_4 of a block of :meth:`transition_blocks`: with ``noise_per_value``, the
        ``alpha_4,k`` of the block's value k, else the shared :attr:`transition_noise`."""
        if not self.noise_per_value:
            return self.transition_noise
        return self.value_noise[self.intentions[self.seq_of_src[rows[0]], 0].long()]

    def estimate_value_noise(self) -> torch.Tensor:
        """Set each ``alpha_4,k`` (:attr:`value_noise`) to its MAP value.

        With the latents X and the transition kernel fixed, ``alpha_4,k`` maximises the GP
        marginal likelihood ``N(X_out^k; 0, K_x(X_in^k) + alpha_4,k I)`` of value k's
        transition pairs (its block of Eq. 5) times the log-normal prior
        ``N(log alpha_4,k; log alpha_4, NOISE_PRIOR_SD^2)`` centred on the shared
        :attr:`transition_noise` (the prior of a learned alpha_4): a 1-D bounded search over
        ``log alpha_4,k`` (scipy's ``minimize_scalar``) between ``NOISE_FLOOR`` and
        ``max(||X_out^k||_2^2 / Dx, alpha_4) e^(4 NOISE_PRIOR_SD)``. The prior matters for a value
        with few pairs, whose likelihood alone is flat down to the floor (one pair fitted by
        its own latents explains itself without noise); for many pairs the likelihood
        dominates. A value without training transitions keeps the shared noise. :meth:`fit`
        calls this at its end when ``noise_per_value=True``.

        Returns:
            The new ``[K]`` :attr:`value_noise`.

        Raises:
            ValueError: the model was not built with ``noise_per_value=True``.
        """
        if not self.noise_per_value:
            raise ValueError("estimate_value_noise() needs a model built with noise_per_value=True")
        with torch.no_grad():
            x = self.latent.detach()
            inputs, targets = self.transition_inputs(x), self.transition_targets(x)
            centre = math.log(float(self.transition_noise))
            sd = self.NOISE_PRIOR_SD
            new = torch.full_like(self.value_noise, float(self.transition_noise))
            for rows in self.transition_blocks():
                code = int(self.intentions[self.seq_of_src[rows[0]], 0])
                k = self.transition_kernel(inputs[rows]).to_dense()
                y = targets[rows] * self.transition_scales  # Eq. 5's columns, scaled

                def neg_log_post(
                    log_noise: float, k: torch.Tensor = k, y: torch.Tensor = y
                ) -> float:
                    c = k + math.exp(log_noise) * torch.eye(len(k), dtype=k.dtype, device=k.device)
                    nll = float(gaussian_nll(c, y, name="transition kernel matrix K_x"))
                    return nll + 0.5 * ((log_noise - centre) / sd) ** 2

                scale = float(torch.linalg.matrix_norm(y, ord=2)) ** 2 / y.shape[1]
                low = math.log(NOISE_FLOOR)
                high = max(math.log(max(scale, NOISE_FLOOR)), centre) + 4.0 * sd
                best = minimize_scalar(
                    neg_log_post, bounds=(low, high), method="bounded", options={"xatol": 1e-6}
                )
                new[code] = max(math.exp(best.x), NOISE_FLOOR)
            self.value_noise.copy_(new)
        return self.value_noise.clone()

    def fit(self, steps: int = 100, **options: Any) -> FitResult:
        """MAP fit (:meth:`GPDM.fit`, same arguments). With ``noise_per_value`` the latents are
        fitted under the shared :attr:`transition_noise` (every ``alpha_4,k`` is reset to it
        first, so repeated fits do not ratchet the noises down), then
        :meth:`estimate_value_noise` sets the per-value noises."""
        if self.noise_per_value:
            with torch.no_grad():
                self.value_noise.fill_(float(self.transition_noise))
        result = super().fit(steps, **options)
        if self.noise_per_value:
            self.estimate_value_noise()
        return result

    def transition_posterior(self) -> GPPosterior:
        """The transition GP ``[x_t, g] -> x_{t+1}`` (detached); with ``noise_per_value`` each
        training pair carries the ``alpha_4,k`` of its value on the diagonal and predictions with
        noise add that of the input's code (``code_noise``)."""
        if not self.noise_per_value:
            return super().transition_posterior()
        with torch.no_grad():
            x = self.latent.detach()
            codes = self.intentions[self.seq_of_src, 0].long()
            return GPPosterior(
                self.transition_kernel,
                self.transition_inputs(x),
                self.transition_targets(x),
                self.value_noise[codes],
                code_noise=self.value_noise,
                scale=self.transition_posterior_scale(),
            )

    def intention_codes(self) -> torch.Tensor:
        """``[J]`` integer codes of a discrete g."""
        if self.intention != "discrete":
            raise ValueError("intention_codes() needs a discrete intention")
        return self.intentions[:, 0].long()

    def set_intentions(self, intentions: Any) -> None:
        """Replace g of every training sequence (same kind and K). With ``noise_per_value``
        the per-value noises go back to the shared one (a code may now mean other sequences;
        :meth:`fit` or :meth:`estimate_value_noise` sets them again)."""
        values, _ = _check_intentions(
            intentions, self.num_sequences, self.intention, self.num_values, self.latent.dtype
        )
        self.intentions.copy_(values.to(self.intentions.device))
        if self.noise_per_value:
            with torch.no_grad():
                self.value_noise.fill_(float(self.transition_noise))

    def _rollout_inputs(self, x: torch.Tensor, g: Any, step: int) -> torch.Tensor:
        if g is None:
            raise ValueError("rollout of an HGPDM needs the exogenous variable g")
        g = as_tensor(g, "g", dtype=x.dtype, device=x.device).reshape(-1)
        if g.numel() != self.intention_dim:
            raise ValueError(f"g must have {self.intention_dim} values, got {g.numel()}")
        code = float(g[0])
        if self.intention == "discrete" and not (code.is_integer() and 0 <= code < self.num_values):
            raise ValueError(f"g must be an integer code in [0, {self.num_values - 1}], got {code}")
        return torch.cat([x, g.expand(*x.shape[:-1], -1)], dim=-1)

    def _data_arguments(self) -> dict[str, Any]:
        data = super()._data_arguments()
        g = self.intentions.clone()
        data["intentions"] = g[:, 0].long() if self.intention == "discrete" else g
        return data

    # ----------------------------------------------------------------- Algorithm 2.1
    @classmethod
    def discover(
        cls,
        sequences: SequencesLike,
        num_styles: int,
        iterations: int = 10,
        *,
        steps: int = 30,
        latent_dim: int = 3,
        init: str = "kmeans",
        seed: int = 0,
        progress: bool = False,
        **kwargs: Any,
    ) -> HGPDM:
        """Unsupervised discovery of a discrete exogenous variable (Algorithm 2.1).

        Alternates (1) assigning each sequence the style that maximises the joint posterior
        ``p(X, beta, W, Z | g)`` given the others, and (2) the MAP fit of X, beta, W, until the
        assignment stops changing or ``iterations`` is reached. Each step can only lower the
        loss, so the algorithm converges to a local optimum.

        Args:
            sequences: J sequences ``[T_j, Dz]``.
            num_styles: K, the number of styles to discover.
            iterations: maximum number of alternations I (the thesis used 100).
            steps: L-BFGS steps of the MAP fit per iteration.
            latent_dim: ``Dx``.
            init: initial assignment: ``"kmeans"`` (k-means on per-sequence summaries of the PCA
                latents: mean position and mean squared step) or ``"random"``.
            seed: seed of the initial assignment.
            progress: show a progress bar.
            **kwargs: passed to the constructor.

        Returns:
            The fitted model; ``model.intention_codes()`` is the discovered assignment and
            ``model.discovery_history`` the loss after each iteration.

        Raises:
            ValueError: ``num_styles``, ``iterations`` or ``steps`` not a positive int, ``seed``
                not a non-negative int, or more styles than sequences.
        """
        for name, value, low in (
            ("num_styles", num_styles, 1),
            ("iterations", iterations, 1),
            ("steps", steps, 1),
            ("seed", seed, 0),
        ):
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
                kind = "a positive int" if low else "a non-negative int"
                raise ValueError(f"{name} must be {kind}, got {value!r}")
        num_styles, iterations, steps = int(num_styles), int(iterations), int(steps)
        seed = int(seed)
        check_choice(init, "init", ("kmeans", "random"))
        kwargs.pop("intention", None)
        model = cls(
            sequences,
            [0] * len(sequences),
            latent_dim,
            intention="discrete",
            num_values=num_styles,
            **kwargs,
        )
        if num_styles > model.num_sequences:
            raise ValueError(
                f"num_styles ({num_styles}) exceeds the number of sequences ({model.num_sequences})"
            )
        rng = np.random.default_rng(seed)
        if init == "random":
            codes = rng.permutation(np.arange(model.num_sequences) % num_styles)
        else:
            feats = trajectory_summaries(model.latent_sequences())
            km = KMeans(num_styles, n_init=10, random_state=int(rng.integers(2**31)))
            codes = km.fit_predict(feats)
        model.set_intentions(codes)
        model.discovery_history = []
        for _ in trange(iterations, disable=not progress, desc="discover styles"):
            changed = model._assign_styles()
            # Each alternation is a partial MAP fit by design (Algorithm 2.1): no warning here;
            # model.fit_result holds the last one.
            model.fit(steps, warn=False)
            model.discovery_history.append(float(model.loss().detach()))
            if not changed:
                break
        return model

    def _assign_styles(self) -> bool:
        """Step 3 of Algorithm 2.1: coordinate-wise best style per sequence. Returns changed."""
        before = self.intention_codes().clone()
        codes = before.clone()
        with torch.no_grad():
            for j in range(self.num_sequences):
                scores = []
                for k in range(self.num_values):
                    codes[j] = k
                    self.set_intentions(codes)
                    # Only the transition term of Eq. 6 depends on g.
                    scores.append(float(self.transition_nll()))
                codes[j] = int(np.argmin(scores))
                self.set_intentions(codes)
        return not torch.equal(before, codes)


class IDDM(HGPDM):
    """Intention-Driven Dynamics Model (Sec. 3.2): an H-GPDM with the tensor-product kernel.

    The transition kernel is ``alpha_1 exp(-alpha_2/2 |x - x'|^2 - alpha_3/2 (g - g')^2)`` for a
    continuous g, and ``delta(g, g') alpha_1 exp(-alpha_2/2 |x - x'|^2)`` for a discrete g (Sec.
    3.2.2, ``alpha_3 = inf``). Here ``alpha_g[0]`` is the thesis's ``alpha_3`` (the g width);
    ``alpha[2]`` (the linear variance) is unused. The measurement kernel is typically
    ``"linear"`` (Eq. 20) for low-dimensional noisy observations.

    With ``phase_width`` (not in the thesis) the transition kernel also has a factor
    ``exp(-(p - p')^2 / (2 w^2))`` over the phase ``p`` of ``x_t``, its frame index from the start
    of its sequence (``w = phase_width`` frames), so the dynamics may change along a stroke whose
    recordings start at a common event (the linear IDDM's per-frame transitions are the limit of
    a small ``w``; a large ``w`` gives back the thesis's kernel). The transition GP's inputs are
    then ``[x_t, g, p_t]``; the online filter
    (:class:`~hgpdm_torch.inference.OnlineIntentionFilter`) counts a stream's phase from its
    (re)start, so streams must start at the frame the training sequences start at; Monte-Carlo
    planning reads it from the belief (:class:`~hgpdm_torch.decision.mcp.Belief` ``phase``).
    Window inference (VB, MAP, Algorithm 3.1) has no frame count and refuses such a model.

    Args:
        sequences: see :class:`HGPDM`.
        intentions: see :class:`HGPDM`.
        latent_dim: see :class:`HGPDM`.
        phase_width: width of the phase factor in frames, or ``None`` (default, the thesis's
            kernel).
        **kwargs: see :class:`HGPDM`.
    """

    kinds = {"discrete": "iddm_discrete", "continuous": "iddm_continuous"}

    def __init__(
        self,
        sequences: SequencesLike,
        intentions: Any,
        latent_dim: int = 3,
        *,
        phase_width: float | None = None,
        **kwargs: Any,
    ) -> None:
        self.phase_width = phase_width  # checked where the kernel is built
        super().__init__(sequences, intentions, latent_dim, **kwargs)
        if phase_width is not None:
            self.phase_width = float(phase_width)
            self._config["phase_width"] = self.phase_width

    def transition_phases(self) -> torch.Tensor:
        """``[m]`` phase of each transition's source ``x_t``: its frame index in its sequence."""
        return (self.src_index - self.first_index[self.seq_of_src]).to(self.latent.dtype)

    def transition_inputs(self, latent: torch.Tensor) -> torch.Tensor:
        """``[m, Dx + Dg]`` inputs ``[x_t, g]`` of the transition GP (``[x_t, g, p_t]`` with
        ``phase_width``)."""
        inputs = super().transition_inputs(latent)
        if self.phase_width is None:
            return inputs
        return torch.cat([inputs, self.transition_phases()[:, None].to(inputs)], dim=-1)

    def _rollout_inputs(self, x: torch.Tensor, g: Any, step: int) -> torch.Tensor:
        inputs = super()._rollout_inputs(x, g, step)
        if self.phase_width is None:
            return inputs
        return torch.cat([inputs, inputs.new_full((*inputs.shape[:-1], 1), float(step))], -1)
