"""MAP optimisation of a model's loss that never stops silently.

:func:`fit_map` minimises ``model.loss()`` (e.g. the negative log posterior of Eq. 6) over the
parameters that require gradients and returns a :class:`FitResult` that says whether the fit
converged and, if not, why. It guards against the failure modes seen on real data:

- **Stalled L-BFGS.** ``torch.optim.LBFGS(max_iter=1)`` allows one function evaluation per step,
  so its strong-Wolfe line search cannot back off: once a trial raises the loss, every later step
  repeats the same rejected trial and the loss goes flat. Here each step may spend up to
  ``max_eval`` evaluations on its line search; a step that does not lower the loss (or fails
  numerically) is undone, the curvature history is cleared and the step retried; if that fails
  too, a backtracking (Armijo) gradient step is taken; only if no decrease is found along the
  gradient either does the fit stop, saying so.
- **Divergence** (e.g. Adam with a large learning rate): a non-finite loss or a numerical failure
  ends the fit, and the parameters are rolled back to the best state seen, with advice.
- **Premature stop.** Convergence is declared only by explicit criteria: the relative loss change
  stays below ``ftol`` for ``patience`` consecutive steps, or the largest gradient entry falls
  below ``gtol``. Otherwise the result says the step budget ran out and how fast the loss was
  still moving; a :class:`ConvergenceWarning` is emitted unless ``warn=False``.

Optional random restarts perturb the starting parameters and keep the best fit.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import torch

from .linalg import CholeskyError
from .progress import tqdm
from .validation import check_choice

__all__ = ["ConvergenceWarning", "FitResult", "fit_map"]

OptimizerLike = str | torch.optim.Optimizer | Callable[..., torch.optim.Optimizer]

# Errors that mean "the loss cannot be evaluated here" (a trial point, not a bug).
_NUMERICAL = (CholeskyError, FloatingPointError, torch.linalg.LinAlgError)


class ConvergenceWarning(UserWarning):
    """A fit ended without meeting its convergence criteria (see ``FitResult.reason``)."""


@dataclass
class FitResult:
    """What a fit did.

    Attributes:
        history: loss at the start and after every accepted step (``steps + 1`` values).
        converged: whether a convergence criterion was met.
        reason: why the fit stopped, in words (also when it converged).
        grad_norm: Euclidean norm of the gradient at the returned parameters.
        steps: optimizer steps taken (accepted or not).
        evaluations: loss-and-gradient evaluations.
        seconds: wall time.
        history_resets: times the L-BFGS curvature history was cleared after a failed step.
        gradient_steps: fallback (backtracking gradient) steps taken.
        rolled_back: whether the parameters were restored to an earlier, better state.
        restarts: losses reached from each random restart (empty without restarts).
    """

    history: list[float]
    converged: bool
    reason: str
    grad_norm: float
    steps: int
    evaluations: int
    seconds: float
    history_resets: int = 0
    gradient_steps: int = 0
    rolled_back: bool = False
    restarts: list[float] = field(default_factory=list)

    @property
    def final_loss(self) -> float:
        """The loss at the returned parameters."""
        return self.history[-1]

    def summary(self) -> dict[str, Any]:
        """JSON-ready digest for experiment tables: converged, reason, steps, losses, time."""
        return {
            "converged": self.converged,
            "reason": self.reason,
            "steps": self.steps,
            "loss": [self.history[0], self.final_loss],
            "grad_norm": self.grad_norm,
            "seconds": round(self.seconds, 2),
        }

    def __str__(self) -> str:
        state = "converged" if self.converged else "NOT converged"
        return (
            f"fit {state} after {self.steps} steps ({self.evaluations} evaluations, "
            f"{self.seconds:.1f} s): loss {self.history[0]:.6g} -> {self.final_loss:.6g}, "
            f"|grad| {self.grad_norm:.3g}; {self.reason}"
        )


class _Objective:
    """Loss and gradient of a model over a fixed parameter list, with evaluation counting.

    ``model.loss()`` raising one of the numerical errors, or returning a non-finite value, is a
    failed evaluation: :meth:`evaluate` returns ``None`` for it.
    """

    def __init__(self, loss_fn: Callable[[], torch.Tensor], params: list[torch.Tensor]) -> None:
        self.loss_fn = loss_fn
        self.params = params
        self.evaluations = 0

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    def evaluate(self) -> float | None:
        """Loss at the current parameters with gradients in ``p.grad``; ``None`` on failure."""
        self.zero_grad()
        self.evaluations += 1
        try:
            with torch.enable_grad():
                value = self.loss_fn()
                if not bool(torch.isfinite(value)):
                    return None
                value.backward()
        except _NUMERICAL:
            self.zero_grad()
            return None
        if not all(p.grad is None or bool(torch.isfinite(p.grad).all()) for p in self.params):
            return None
        return float(value.detach())

    def grad_vector(self) -> torch.Tensor:
        return torch.cat(
            [(torch.zeros_like(p) if p.grad is None else p.grad).reshape(-1) for p in self.params]
        )

    def snapshot(self) -> list[torch.Tensor]:
        return [p.detach().clone() for p in self.params]

    def restore(self, state: list[torch.Tensor]) -> None:
        with torch.no_grad():
            for p, s in zip(self.params, state, strict=True):
                p.copy_(s)

    def move(self, direction: list[torch.Tensor], step: float) -> None:
        with torch.no_grad():
            for p, d in zip(self.params, direction, strict=True):
                p.add_(d, alpha=step)


def _make_optimizer(
    optimizer: OptimizerLike, params: list[torch.Tensor], lr: float | None, max_eval: int
) -> torch.optim.Optimizer:
    if isinstance(optimizer, str):
        check_choice(optimizer, "optimizer", ("lbfgs", "adam"))
        if optimizer == "lbfgs":
            return torch.optim.LBFGS(
                params,
                lr=lr or 1.0,
                max_iter=1,
                # Without max_eval torch allows int(1.25 * max_iter) = 1 evaluation per step,
                # which leaves the line search no room to back off (see the module docstring).
                max_eval=max_eval,
                history_size=50,
                line_search_fn="strong_wolfe",
                tolerance_grad=0.0,
                tolerance_change=0.0,
            )
        return torch.optim.Adam(params, lr=lr or 0.01)
    if lr is not None:
        raise ValueError("lr applies to the named optimizers only; configure your optimizer")
    if isinstance(optimizer, torch.optim.Optimizer):
        return _check_holds_parameters(optimizer, params, "optimizer")
    if callable(optimizer):
        made = optimizer(params)
        if not isinstance(made, torch.optim.Optimizer):
            raise TypeError(
                f"the optimizer factory returned {type(made).__name__}, not an Optimizer"
            )
        return _check_holds_parameters(made, params, "the optimizer factory's optimizer")
    raise TypeError(f"optimizer must be a name, an Optimizer or a factory, got {optimizer!r}")


def _check_holds_parameters(
    opt: torch.optim.Optimizer, params: list[torch.Tensor], name: str
) -> torch.optim.Optimizer:
    """``opt`` if it updates at least one of the trainable ``params``; an optimizer over other
    tensors would leave the model as it is, and the fit would stall without a cause."""
    own = {id(p) for p in params}
    if not any(id(p) in own for group in opt.param_groups for p in group["params"]):
        raise ValueError(
            f"{name} ({type(opt).__name__}) holds none of the model's trainable parameters: "
            "build it over model.parameters(), e.g. torch.optim.Adam(model.parameters()), or "
            "pass a factory params -> optimizer"
        )
    return opt


def _clear_history(opt: torch.optim.Optimizer) -> None:
    """Forget L-BFGS curvature pairs (or Adam moments): the next step starts afresh."""
    opt.state.clear()


def _gradient_step(obj: _Objective, loss: float, max_tries: int = 40) -> float | None:
    """Backtracking (Armijo) step along the negative gradient from the current parameters.

    The first trial moves the largest parameter entry by 0.1; each failure halves the step.
    Returns the new loss, or ``None`` (parameters unchanged) if no trial lowers the loss.
    """
    grads = [torch.zeros_like(p) if p.grad is None else p.grad.detach().clone() for p in obj.params]
    g2 = sum(float(g.pow(2).sum()) for g in grads)
    gmax = max(float(g.abs().max()) for g in grads)
    if g2 == 0.0 or not math.isfinite(g2):
        return None
    start = obj.snapshot()
    step = 0.1 / gmax
    direction = [-g for g in grads]
    for _ in range(max_tries):
        obj.move(direction, step)
        value = obj.evaluate()
        if value is not None and value <= loss - 1e-4 * step * g2 and value < loss:
            return value
        obj.restore(start)
        step *= 0.5
    obj.evaluate()  # gradients of the unchanged parameters again
    return None


def _steps_message(lr: float | None, optimizer: OptimizerLike) -> str:
    if optimizer == "adam" or isinstance(optimizer, torch.optim.Adam):
        return "lower the learning rate (lr)"
    return "lower the learning rate, standardise the data, or raise the noise lower bounds"


def _run(
    obj: _Objective,
    opt: torch.optim.Optimizer,
    steps: int,
    *,
    ftol: float,
    gtol: float,
    patience: int,
    progress: bool,
    desc: str,
    advice: str,
) -> FitResult:
    is_lbfgs = isinstance(opt, torch.optim.LBFGS)
    start_time = time.perf_counter()
    loss = obj.evaluate()
    if loss is None:
        raise FloatingPointError(
            "the loss is not finite (or its kernel matrix not positive definite) at the "
            "starting parameters; check the data for outliers or constant channels and "
            "standardise it"
        )
    history = [loss]
    best_loss, best_state = loss, obj.snapshot()
    resets = gradient_steps = quiet = taken = 0
    converged, reason, rolled_back = False, "", False
    cached = True  # p.grad holds the gradient of the current parameters

    def closure() -> torch.Tensor:
        nonlocal cached
        if cached:  # the optimizer's first call of a step: reuse the evaluation just made
            cached = False
            return torch.tensor(
                history[-1], dtype=torch.float64, device="cpu"
            )  # a host scalar: no device copy
        value = obj.evaluate()
        if value is None:
            raise FloatingPointError("trial point failed")
        return torch.tensor(value, dtype=torch.float64, device="cpu")

    def attempt() -> float | None:
        """One optimizer step; the loss after it, or ``None`` if a trial point failed."""
        nonlocal cached
        try:
            opt.step(closure)
            value = obj.evaluate()
        except FloatingPointError:
            value = None
        cached = True
        return value

    bar = tqdm(total=steps, disable=not progress, desc=desc)
    try:
        for taken in range(1, steps + 1):
            new = attempt()
            if is_lbfgs and (new is None or not new < loss):
                # A failed or zero step: undo it, forget the curvature history, retry once.
                # (Accepted L-BFGS steps always lower the loss: each step starts from the best
                # state.)
                obj.restore(best_state)
                _clear_history(opt)
                resets += 1
                obj.evaluate()
                new = attempt()
                if new is None or not new < loss:
                    obj.restore(best_state)
                    _clear_history(opt)
                    obj.evaluate()
                    new = _gradient_step(obj, loss)
                    gradient_steps += new is not None
                    if new is None:
                        grad = float(obj.grad_vector().abs().max())
                        converged = grad <= gtol * max(1.0, abs(loss))
                        reason = (
                            "no step along the L-BFGS direction or the gradient lowers the loss: "
                            f"a stationary point to numerical precision (max |grad| {grad:.3g})"
                        )
                        if not converged:
                            reason += (
                                "; the objective may be non-smooth here (near-singular kernel "
                                "matrices): " + advice
                            )
                        break
                    cached = True
            if new is None:  # a first-order optimizer hit a numerical failure: diverged
                obj.restore(best_state)
                rolled_back = True
                reason = (
                    f"diverged at step {taken} (the loss could not be evaluated); rolled back to "
                    f"the best state (loss {best_loss:.6g}): {advice}"
                )
                break
            history.append(new)
            change = (loss - new) / max(1.0, abs(new))
            loss = new
            if loss < best_loss:
                best_loss, best_state = loss, obj.snapshot()
            elif loss - best_loss > max(1.0, abs(best_loss)):
                obj.restore(best_state)
                rolled_back = True
                reason = (
                    f"diverged at step {taken} (loss {loss:.6g}, best {best_loss:.6g}); rolled "
                    f"back to the best state: {advice}"
                )
                break
            bar.update(1)
            bar.set_postfix(loss=f"{loss:.6g}")
            gmax = float(obj.grad_vector().abs().max())
            quiet = quiet + 1 if abs(change) < ftol else 0
            if gmax <= gtol * max(1.0, abs(loss)):
                converged, reason = True, f"gradient below gtol (max |grad| {gmax:.3g})"
                break
            if quiet >= patience:
                converged = True
                reason = f"relative loss change below ftol={ftol:g} for {patience} steps"
                break
        else:
            rel = (history[max(0, len(history) - 6)] - loss) / max(1.0, abs(loss))
            reason = (
                f"reached the step limit ({steps}) while the loss still fell by {rel:.2e} "
                "(relative) over the last 5 steps: call fit again or raise steps"
            )
    finally:
        bar.close()
    if not rolled_back and best_loss < loss:  # a first-order method may end above its best
        obj.restore(best_state)
        rolled_back = True
    final = obj.evaluate()
    if final is None:  # cannot happen for a state that evaluated before; be explicit anyway
        raise FloatingPointError("the loss of the returned parameters is not finite")
    if history[-1] != final:
        history.append(final)
    return FitResult(
        history=history,
        converged=converged,
        reason=reason,
        grad_norm=float(obj.grad_vector().norm()),
        steps=taken if steps else 0,
        evaluations=obj.evaluations,
        seconds=time.perf_counter() - start_time,
        history_resets=resets,
        gradient_steps=gradient_steps,
        rolled_back=rolled_back,
    )


def _perturbed_starts(
    params: list[torch.Tensor], restarts: int, scale: float, seed: int
) -> Iterator[list[torch.Tensor]]:
    gen = torch.Generator().manual_seed(seed)
    base = [p.detach().clone() for p in params]
    for _ in range(restarts):
        yield [
            b
            + scale
            * b.std().nan_to_num(1.0).clamp_min(1e-3)
            * torch.randn(b.shape, generator=gen, dtype=b.dtype, device=gen.device).to(b.device)
            if b.numel() > 1
            else b.clone()
            for b in base
        ]


def fit_map(
    model: torch.nn.Module,
    steps: int = 100,
    *,
    optimizer: OptimizerLike = "lbfgs",
    lr: float | None = None,
    ftol: float = 1e-9,
    gtol: float = 1e-6,
    patience: int = 3,
    max_eval: int = 25,
    restarts: int = 0,
    restart_scale: float = 0.1,
    seed: int = 0,
    warn: bool = True,
    progress: bool = False,
    loss: Callable[[], torch.Tensor] | None = None,
) -> FitResult:
    """Minimise ``model.loss()`` over the model's trainable parameters.

    Args:
        model: a torch module with a ``loss()`` method returning a scalar tensor.
        steps: maximum optimizer steps (>= 0).
        optimizer: ``"lbfgs"`` (default: strong-Wolfe line search with up to ``max_eval``
            evaluations a step, history reset and gradient fallback on failed steps),
            ``"adam"``, an optimizer over ``model.parameters()``, or a factory
            ``params -> optimizer``.
        lr: learning rate of a named optimizer (L-BFGS default 1, Adam 0.01).
        ftol: converged when ``|L_k - L_{k+1}| / max(1, |L_{k+1}|) < ftol`` for ``patience``
            consecutive steps.
        gtol: converged when the largest gradient entry is ``<= gtol * max(1, |L|)``.
        patience: see ``ftol``.
        max_eval: evaluations an L-BFGS line search may spend per step.
        restarts: extra fits from randomly perturbed starting parameters; the best is kept.
        restart_scale: perturbation of each parameter tensor, in units of its standard deviation.
        seed: seed of the restart perturbations.
        warn: emit a :class:`ConvergenceWarning` when the fit does not converge.
        progress: show a tqdm progress bar.
        loss: the objective (default ``model.loss``).

    Returns:
        A :class:`FitResult`. The model holds the best parameters found.

    Raises:
        ValueError: for non-positive tolerances or counts, unknown optimizer names, or an
            optimizer that holds none of the model's trainable parameters.
        FloatingPointError: when the loss cannot be evaluated at the starting parameters.
    """
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 0:
        raise ValueError(f"steps must be a non-negative int, got {steps!r}")
    for name, value in (("ftol", ftol), ("gtol", gtol), ("restart_scale", restart_scale)):
        if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    for name, value, low in (("patience", patience, 1), ("max_eval", max_eval, 2)):
        if not isinstance(value, int) or isinstance(value, bool) or value < low:
            raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
    if not isinstance(restarts, int) or isinstance(restarts, bool) or restarts < 0:
        raise ValueError(f"restarts must be a non-negative int, got {restarts!r}")
    if lr is not None and not (isinstance(lr, int | float) and math.isfinite(lr) and lr > 0):
        raise ValueError(f"lr must be a positive finite number, got {lr!r}")
    if restarts and not isinstance(optimizer, str):
        raise ValueError("restarts need a named optimizer (a fresh one is built per start)")
    params = [p for p in model.parameters() if p.requires_grad]
    if not params:
        raise ValueError("the model has no parameter that requires a gradient")
    loss_fn = loss if loss is not None else model.loss
    desc = f"fit {type(model).__name__}"
    advice = _steps_message(lr, optimizer)
    was_training = model.training
    model.train()
    try:
        obj = _Objective(loss_fn, params)
        opt = _make_optimizer(optimizer, params, lr, max_eval)
        kw: dict[str, Any] = dict(
            ftol=ftol, gtol=gtol, patience=patience, progress=progress, desc=desc, advice=advice
        )
        result = _run(obj, opt, steps, **kw)
        if restarts:
            best_state, finals = obj.snapshot(), [result.final_loss]
            for start in _perturbed_starts(best_state, restarts, restart_scale, seed):
                obj.restore(start)
                try:
                    trial = _run(obj, _make_optimizer(optimizer, params, lr, max_eval), steps, **kw)
                except FloatingPointError:
                    finals.append(math.inf)
                    continue
                finals.append(trial.final_loss)
                if trial.final_loss < result.final_loss:
                    result, best_state = trial, obj.snapshot()
            obj.restore(best_state)
            obj.evaluate()
            result.restarts = finals
            result.evaluations = obj.evaluations
    finally:
        obj.zero_grad()
        model.train(was_training)
    if warn and not result.converged:
        warnings.warn(str(result), ConvergenceWarning, stacklevel=2)
    return result
