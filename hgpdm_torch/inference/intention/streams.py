"""B independent streams of one online filter, isolated from each other bit for bit.

:class:`IsolatedStreams` holds the per-stream state of an online filter (the shared Gaussian
``q(x_t)`` and the log belief over K intention values of each of B streams) and runs its update
so that nothing one stream receives or computes changes another's result: streams are updated in
chunks that are fixed ranges of stream indices, each computing all its streams; a bad
observation is rejected for its stream only; a stream whose update fails numerically is found by
bisection and restarted at the prior. The filter's algorithm itself (Algorithm 3.2) is the
subclass's :meth:`~IsolatedStreams._step` and :meth:`~IsolatedStreams._initialise`
(:class:`~hgpdm_torch.inference.intention.online.OnlineIntentionFilter`).

Two pieces are shared with every online belief of the toolkit (:class:`~hgpdm_torch.models.
LinearIDDMStream` uses both), so that all treat a frame the same way:
:func:`~hgpdm_torch.observations.screen_observations` (the shape check of one update's rows and
the rejection of bad rows, which then count as missing) and
:func:`~hgpdm_torch.intention_belief.belief_step` (the forgetful, tempered belief recursion of
Algorithm 3.2, lines 10-11).

Shapes: ``B`` streams, ``K`` intention values, ``Dx`` latent, ``Dz`` observed dims.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch

from ...intention_belief import IntentionBelief, flagged_belief
from ...linalg import CholeskyError, positive_definite
from ...observations import ObservationCheck, screen_observations

if TYPE_CHECKING:
    from .options import FilterOptions

__all__ = ["IsolatedStreams"]

#: What a failed update of one stream raises: a covariance that does not factorise
#: (:func:`~hgpdm_torch.linalg.psd_cholesky`: ``CholeskyError``, or ``ValueError`` for NaN/inf),
#: or a LAPACK failure. The online filter isolates the stream and restarts it.
_NUMERICAL_ERRORS = (CholeskyError, torch.linalg.LinAlgError, ValueError)
#: Streams initialised together (a measurement update is cheap; fixed ranges, see ``update``).
_INIT_CHUNK = 4096


def _usable_state(mean: torch.Tensor, cov: torch.Tensor, log_belief: torch.Tensor) -> torch.Tensor:
    """``[B]`` mask of streams whose mean ``[B, Dx]``, covariance ``[B, Dx, Dx]`` and log belief
    ``[B, K]`` are usable: the sum of the means, the covariance entries and the largest log
    belief is finite (no entry is NaN or +-inf, or so large, ~1e307, that the sum overflows,
    except -inf log beliefs, zero probabilities, of which not all), and the covariance is
    positive definite up to rounding (:func:`~hgpdm_torch.linalg.positive_definite`). Both are
    computed on the device and read with the one synchronisation per update the caller needs
    anyway, so an indefinite state restarts its stream whether or not ``settings.debug`` is on."""
    finite = torch.isfinite(mean.sum(-1) + cov.sum((-2, -1)) + log_belief.amax(-1))
    return finite & positive_definite(cov)


class IsolatedStreams:
    """Base of an online filter over B isolated streams (module docstring).

    A subclass sets, before calling :meth:`reset`: ``batch_size`` (B), ``values [K, Dg]``,
    ``continuous`` (whether g is continuous), ``mu0 [Dx]``, ``Sigma0 [Dx, Dx]`` and
    ``log_prior [K]`` (the state of an unstarted stream, in the filter's ``dtype``),
    ``check`` (an :class:`~hgpdm_torch.observations.ObservationCheck`), ``obs_dim`` (Dz),
    ``chunk_size`` and ``options`` (a
    :class:`~hgpdm_torch.inference.intention.options.FilterOptions`; with
    ``options.observations.strict`` a bad row or a failed stream raises); and implements
    ``_initialise`` (a stream's first observation) and ``_step`` (every later one), both
    ``(mean [S, Dx], cov [S, Dx, Dx], log_belief [S, K], z [S, Dz], phase [S]) -> (mean, cov,
    log_belief)`` on a chunk of S streams, raising one of ``_NUMERICAL_ERRORS`` where they fail
    numerically. ``phase`` is the frame index of the state updated from, counted in rows since
    the stream's (re)start (``steps - 1``; the phase of a phase-aware IDDM's ``x_t``).
    """

    batch_size: int
    values: torch.Tensor
    continuous: bool
    mu0: torch.Tensor
    Sigma0: torch.Tensor
    log_prior: torch.Tensor
    check: ObservationCheck
    dtype: torch.dtype
    obs_dim: int
    chunk_size: int
    options: FilterOptions
    _initialise: Callable[..., tuple[torch.Tensor, torch.Tensor, torch.Tensor]]
    _step: Callable[..., tuple[torch.Tensor, torch.Tensor, torch.Tensor]]

    @property
    def num_values(self) -> int:
        """K, the number of intention values."""
        return self.values.shape[0]

    def _stream_index(self, streams: Any) -> torch.Tensor:
        """Stream indices ``[S]`` (int64, in ``[0, B)``) from indices or a ``[B]`` bool mask."""
        B = self.batch_size
        try:
            idx = torch.as_tensor(streams, device=self.mean.device)
        except (TypeError, ValueError, RuntimeError) as err:
            raise TypeError(f"streams must be stream indices or a [B] bool mask: {err}") from err
        if idx.numel() == 0:
            return idx.new_zeros(0, dtype=torch.long)
        if idx.dtype == torch.bool:
            if idx.shape != (B,):
                raise ValueError(f"a streams mask must have shape [B] = [{B}], got {idx.shape}")
            return torch.nonzero(idx).flatten()
        if idx.is_floating_point() or idx.is_complex():
            raise TypeError(f"streams must be integer indices or a bool mask, got {idx.dtype}")
        idx = idx.reshape(-1).long()
        if bool(((idx < -B) | (idx >= B)).any()):
            raise ValueError(f"streams must be indices in [-{B}, {B}), got {idx.tolist()}")
        return idx % B

    def reset(self, streams: Any = None) -> None:
        """Restart streams at the prior and zero their ``steps``, ``rejected_count`` and
        ``reset_count``.

        Args:
            streams: ``None`` (all streams), stream indices (an int or a sequence/tensor of
                ints, negative ones counting from the end) or a ``[B]`` bool mask. An empty
                selection is a no-op.
        """
        if streams is None:
            B, dx, K = self.batch_size, self.mu0.shape[0], self.num_values
            like = self.mu0  # the state lives on the model's device, in the filter's dtype
            self.mean = like.new_empty(B, dx, dtype=self.dtype)
            self.cov = like.new_empty(B, dx, dx, dtype=self.dtype)
            self.log_belief = like.new_empty(B, K, dtype=self.dtype)
            self.started = like.new_zeros(B, dtype=torch.bool)
            self.steps = like.new_zeros(B, dtype=torch.long)
            self.rejected_count = like.new_zeros(B, dtype=torch.long)
            self.reset_count = like.new_zeros(B, dtype=torch.long)
            idx: Any = slice(None)
        else:
            idx = self._stream_index(streams)
            if idx.numel() == 0:
                return
        self.mean[idx] = self.mu0
        self.cov[idx] = self.Sigma0
        self.log_belief[idx] = self.log_prior
        self.started[idx] = False
        self.steps[idx] = 0
        self.rejected_count[idx] = 0
        self.reset_count[idx] = 0

    def belief(self) -> IntentionBelief:
        """The current posterior over intentions, ``prob [B, K]`` (no ``rejected`` flags)."""
        return IntentionBelief.from_log(self.log_belief, self.values, self.continuous)

    def update(self, z: Any) -> IntentionBelief:
        """Process one observation per stream (Algorithm 3.2, lines 5-11).

        Args:
            z: ``[B, Dz]`` observations (``[Dz]`` when B = 1); a NaN row is a missing
                observation of that stream. A bad row (inf, partly NaN, or implausible; see
                the class docstring) is rejected for its stream only (``strict``: raises).

        Returns:
            The posterior after this step: ``prob [B, K]`` (``[K]`` for a ``[Dz]`` input), for a
            continuous g its ``mean`` and ``std``, and the flags ``rejected`` and
            ``reset_streams`` ``[B]`` (``[]``).

        Raises:
            ValueError: a wrong shape; with ``strict``, a bad observation or a failed stream
                (naming the stream, step and channel); the filter's state is then unchanged.
        """
        B = self.batch_size
        z, rejected, single = screen_observations(
            z, self.check, B, self.obs_dim, device=self.mean.device,
            strict=self.options.observations.strict, where=self._where,
        )  # fmt: skip
        z = z.to(self.dtype)
        # the update works on copies, written back at the end: a strict error changes nothing
        mean, cov, log_belief = self.mean.clone(), self.cov.clone(), self.log_belief.clone()
        started = self.started.clone()
        broken = ~_usable_state(mean, cov, log_belief)
        any_broken = bool(broken.any())
        if any_broken:
            self._fail(int(torch.nonzero(broken)[0]), "holds a non-finite or indefinite state")
            self._restart(broken, mean, cov, log_belief, started)
        failed = torch.zeros_like(broken)
        new = ~started
        num_new = int(new.sum())
        self._chunks(mean, cov, log_belief, z, new, num_new, failed)
        if num_new:
            started |= new & ~torch.isnan(z).all(-1)
        failed |= ~_usable_state(mean, cov, log_belief)
        any_failed = bool(failed.any())
        if any_failed:
            self._fail(int(torch.nonzero(failed)[0]), "gave a non-finite or indefinite state")
            self._restart(failed, mean, cov, log_belief, started)
        for attr, value in (
            ("mean", mean), ("cov", cov), ("log_belief", log_belief), ("started", started),
        ):  # fmt: skip
            getattr(self, attr).copy_(value)
        del mean, cov, log_belief, started, value  # copied: their memory serves the belief below
        self.steps += 1
        reset = broken | failed
        if any_broken or any_failed:
            # a stream restarted before its step counts this observation, one that failed not
            self.steps.copy_(torch.where(broken, 1, self.steps).masked_fill_(failed, 0))
            self.reset_count += reset
        self.rejected_count += rejected
        return flagged_belief(
            self.log_belief, self.values, self.continuous, single, rejected, reset
        )

    def _chunks(
        self,
        mean: torch.Tensor,
        cov: torch.Tensor,
        log_belief: torch.Tensor,
        z: torch.Tensor,
        new: torch.Tensor,
        num_new: int,
        failed: torch.Tensor,
    ) -> None:
        """:meth:`update`'s steps and initialisations of ``new [B]`` streams, chunk after chunk,
        into ``mean``, ``cov`` and ``log_belief`` (``failed [B]`` marks the failing streams); in
        a method of its own so that its temporaries are gone when the belief is formed."""
        B = self.batch_size
        # Chunks are fixed ranges of streams and compute every stream of their range, the
        # inactive ones unobserved and discarded: the shapes, and so the rounding, of a stream's
        # update do not depend on which other streams are new, rejected or failing. The step
        # runs first: it reads the state of the new streams before they are initialised.
        for fn, active, size, targets, count in (
            (self._step, ~new, self.chunk_size, (mean, cov, log_belief), B - num_new),
            (self._initialise, new, _INIT_CHUNK, (mean, cov, log_belief), num_new),
        ):
            if count == 0:
                continue
            every = count == B
            inputs = (
                mean,
                cov,
                log_belief,
                z if every else z.masked_fill(~active[:, None], math.nan),
                (self.steps - 1).to(self.dtype),
            )
            for start in range(0, B, size):
                rows = slice(start, start + size)
                act = active[rows]
                if not every and not bool(act.any()):
                    continue
                out = self._guarded(fn, rows, inputs, act, failed)
                for target, value in zip(targets, out, strict=True):
                    if not every:
                        keep = act.view(-1, *([1] * (value.dim() - 1)))
                        value = torch.where(keep, value, target[rows])
                    target[rows] = value

    def _where(self, b: int) -> str:
        return f"z[{b}] (stream {b}, step {int(self.steps[b])})"

    def _fail(self, b: int, what: str, err: Exception | None = None) -> None:
        """With ``strict``, raise for stream ``b`` (else the caller restarts it)."""
        if self.options.observations.strict:
            cause = f": {err}" if err is not None else ""
            raise ValueError(
                f"stream {b} at step {int(self.steps[b])} {what}{cause} (with strict=False it "
                "would be restarted at the prior)"
            ) from err

    def _guarded(
        self,
        fn: Callable[..., tuple[torch.Tensor, ...]],
        rows: slice,
        inputs: tuple[torch.Tensor, ...],
        active: torch.Tensor,
        failed: torch.Tensor,
    ) -> tuple[torch.Tensor, ...]:
        """``fn`` on the streams ``rows`` of ``inputs`` (``mean, cov, log_belief, z, phase``,
        ``[B, ..]``).

        Where it fails numerically (``_NUMERICAL_ERRORS``), bisection finds the streams that fail
        on their own; the active ones among them are marked in ``failed [B]`` (``strict``:
        raised), and ``fn`` is run again on all ``rows`` with those streams at the prior and
        unobserved, so that the others get the results (bit for bit) they get without them.
        """
        args = tuple(x[rows] for x in inputs)
        try:
            return fn(*args)
        except _NUMERICAL_ERRORS as err:
            error = err
        pos = torch.arange(len(active), device=active.device)
        bad = self._bisect(fn, args, pos, active, rows.start, error)
        if len(bad) == 0:  # no stream fails on its own: not a failure of a stream
            raise error
        failed[rows.start + bad[active[bad]]] = True
        args = tuple(a.clone() for a in args)
        priors = (self.mu0, self.Sigma0, self.log_prior, math.nan)
        for a, prior in zip(args[:4], priors, strict=True):  # the phase stays
            a[bad] = prior
        return fn(*args)

    def _bisect(
        self,
        fn: Callable[..., tuple[torch.Tensor, ...]],
        args: tuple[torch.Tensor, ...],
        pos: torch.Tensor,
        active: torch.Tensor,
        offset: int,
        error: Exception | None = None,
    ) -> torch.Tensor:
        """The positions among ``pos`` at which ``fn`` fails on a single stream (``error``:
        how ``fn`` already failed on all of ``pos``)."""
        if error is None:
            try:
                fn(*(a[pos] for a in args))
                return pos[:0]
            except _NUMERICAL_ERRORS as err:
                error = err
        if len(pos) == 1:
            if bool(active[pos[0]]):
                self._fail(offset + int(pos[0]), "failed numerically", error)
            return pos
        half = len(pos) // 2
        first = self._bisect(fn, args, pos[:half], active, offset)
        return torch.cat([first, self._bisect(fn, args, pos[half:], active, offset)])

    def _restart(
        self,
        streams: torch.Tensor,
        mean: torch.Tensor,
        cov: torch.Tensor,
        log_belief: torch.Tensor,
        started: torch.Tensor,
    ) -> None:
        """Put the ``[B]`` mask ``streams`` of the given state tensors back at the prior."""
        mean[streams] = self.mu0
        cov[streams] = self.Sigma0
        log_belief[streams] = self.log_prior
        started[streams] = False
