"""Problem (38) against a reference that shares no code with :mod:`hgpdm_torch.decision`.

Both solvers of :mod:`hgpdm_torch.decision.opponent` (the online :class:`DeltaSafeResponder`
and the cutting-plane :func:`solve_delta_safe` that ``test_opponent.py`` holds it to) call the
same inner routine for the worst opponent in the ball, so a bug there would pass unseen. The
reference here is built from the thesis's definitions (Sec. 5.2.1-5.2.2) with scipy only; the
game matrices are the only thing it takes from the toolkit.

Definitions. ``p`` is the empirical distribution of the opponent's ``N`` observed actions,
``eps = ((|Aj| - 1) ln(N + 1) - ln(delta / |S|)) / N`` the KL radius, the opponent model
``Omega = {q in simplex : KL(p || q) <= eps}``, and Problem (38) is

    V = max_{pi in simplex} phi(pi),    phi(pi) = min_{q in Omega} pi^T R q.

Reference, three pieces, each a certified bound however inaccurate the optimiser behind it:

- inner lower bound: weak Lagrange duality of ``min_q c^T q`` over ``Omega`` (the multiplier
  ``lambda`` of the KL constraint eliminated in closed form) gives, for every
  ``mu <= min_k c_k``, ``phi >= g(mu) = mu + e^-eps prod_{k: p_k > 0} (c_k - mu)^{p_k}``; the
  best ``mu`` is the root of ``g'`` (``brentq``), or ``min c`` where ``g`` still rises there.
- inner upper bound: ``c^T q`` for a member ``q`` of ``Omega``: the stationarity point
  ``q_k = lambda p_k / (c_k - mu)`` or ``p`` restricted to the cheapest actions, membership
  checked with our own KL (a point slightly outside is pulled towards ``p`` until inside).
- outer: ``L = phi(pi_L)`` (lower bound as above) at the ``pi_L`` found by SLSQP on the
  jointly concave ``max_{pi, mu} g(pi, mu)`` (or on ``phi`` itself), and, by Sion's minimax
  theorem, ``V = min_{q in Omega} max_i (R q)_i <= U = max_i (R q_U)_i`` for the member
  ``q_U`` found by SLSQP on the epigraph form of that convex problem (the support entries of
  ``q`` in log space, which makes the KL constraint linear). ``eps = 0`` (best response to
  ``p``) and ``eps = inf`` (the minimax LP) are solved exactly.

So ``L <= V <= U`` rigorously, up to float rounding (below 1e-12 here), and every comparison
first requires the reference to close its own gap ``U - L`` to ``1e-9`` times the reward range
(in practice it reaches ~1e-15). The value tolerances are then that gap, plus the gap the
toolkit certifies for itself (its ``tol``), plus ``1e-12`` of rounding; nothing is tuned to the
toolkit's output. Strategies: every member ``q`` gives ``pi^T R q >= phi(pi)``, so the cuts
``pi^T R q_l >= V - eta`` for a few members ``q_l`` bound a polytope holding every strategy
within ``eta`` of the optimum; its box (by LP) is a certified outer bound. When that box is
narrow (<= 1e-2) the optimum is unique and the toolkit's strategies must equal ``pi_L`` to the
box's width (in practice ~1e-4 or less), as must the expected payoff against the model's
centre, ``pi^T R p``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import pytest
from scipy.optimize import brentq, linprog, minimize

from hgpdm_torch.decision.games import RPS_REWARD, TABLE_TENNIS_REWARD, two_stage_rps
from hgpdm_torch.decision.opponent import (
    DeltaSafeResponder,
    KLBall,
    delta_safe_tree,
    kl_bound,
    solve_delta_safe,
)

_SLSQP = {"ftol": 1e-15, "maxiter": 300}
_REF_GAP = 1e-9  # the reference must certify U - L below this, relative to the reward range
_ROUND = 1e-12  # float rounding in values of order one
_LP_TIGHT = {"primal_feasibility_tolerance": 1e-10, "dual_feasibility_tolerance": 1e-10}

# ---------------------------------------------------------------- the independent reference


def _ref_radius(delta: float, n: int, n_actions: int, n_states: int = 1) -> float:
    """Sec. 5.2.1 and 5.3: ``eps = ((|Aj| - 1) ln(N + 1) - ln(delta / |S|)) / N``."""
    if n == 0:
        return math.inf
    return ((n_actions - 1) * math.log(n + 1) - math.log(delta / n_states)) / n


def _ref_kl(p: np.ndarray, q: np.ndarray) -> float:
    on = p > 0
    if (q[on] <= 0).any():
        return math.inf
    return float(np.sum(p[on] * np.log(p[on] / q[on])))


def _dual(c: np.ndarray, p: np.ndarray, eps: float, mu: float) -> float:
    """``g(mu)``, a lower bound on ``min_{q in Omega} c^T q`` for any ``mu <= min c``."""
    d = c[p > 0] - mu
    if (d <= 0).any():
        return mu
    return mu + math.exp(-eps + float(p[p > 0] @ np.log(d)))


def _into_ball(q: np.ndarray, p: np.ndarray, eps: float) -> np.ndarray:
    """``q`` renormalised, then moved along the segment to ``p`` until ``KL(p || q) <= eps``."""
    on = p > 0
    p_on, neg_entropy = p[on], float(p[on] @ np.log(p[on]))

    def inside(v: np.ndarray) -> bool:
        return bool((v[on] > 0).all()) and neg_entropy - float(p_on @ np.log(v[on])) <= eps

    q = np.clip(q, 0.0, None)
    q = q / q.sum()
    if inside(q):
        return q
    # KL(p || (1 - t) q + t p) is convex in t and zero at t = 1, so monotone: the smallest t
    # on a decade grid, then bisection to a relative 1e-6 (the candidates are mostly outside
    # by rounding, t ~ 1e-14)
    lo = 0.0
    for hi in 10.0 ** np.arange(-16.0, 1.0):
        if inside((1 - hi) * q + hi * p):
            break
        lo = hi
    while hi - lo > 1e-6 * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if inside((1 - mid) * q + mid * p) else (mid, hi)
    return (1 - hi) * q + hi * p


def _worst(c: np.ndarray, p: np.ndarray, eps: float) -> tuple[float, float, np.ndarray]:
    """``(lower, upper, q)``: certified bounds on ``min_{q in Omega} c^T q``, ``q`` a member."""
    return _inner(c, p, eps)[:3]


def _inner(c: np.ndarray, p: np.ndarray, eps: float) -> tuple[float, float, np.ndarray, float]:
    """:func:`_worst` and the dual variable ``mu`` that certifies the lower bound."""
    c = np.asarray(c, dtype=float)
    if eps == 0.0:  # the ball is the point p
        return float(c @ p), float(c @ p), p.copy(), -math.inf
    if math.isinf(eps):  # the whole simplex
        q = np.zeros_like(p)
        q[np.argmin(c)] = 1.0
        return float(c.min()), float(c.min()), q, float(c.min())
    w = math.exp(-eps)
    on = p > 0
    top = float(c.min())
    # below `low`, g(mu) < min c <= g(top) by AM-GM: the maximiser lies in [low, top]
    low = top - w * float(np.ptp(c)) / (1.0 - w) - 1.0

    def slope(u: float) -> float:
        """``ln(1 - g'(mu)) = ln(lambda sum_k p_k / (c_k - mu))`` at ``mu = top - e^u``."""
        d = (c[on] - top) + math.exp(u)
        return -eps + float(p[on] @ np.log(d)) + math.log(float(np.sum(p[on] / d)))

    # g is concave, so the slope is increasing in mu; its root (if below top) is the maximiser,
    # found in u = ln(top - mu) for relative accuracy when mu is very close to top
    u_lo, u_hi = -690.0, math.log(top - low)
    mus, d_root = [top], None  # no root: g' >= 0 up to top, the maximiser is the boundary
    if slope(u_lo) > 0.0 and slope(u_hi) < 0.0:
        u = brentq(slope, u_lo, u_hi, xtol=1e-14, maxiter=500)
        d_root = (c - top) + math.exp(u)
        mus.append(top - math.exp(u))
    mu = max(mus, key=lambda m: _dual(c, p, eps, m))
    lower = _dual(c, p, eps, mu)
    # members of the ball: the stationarity point q_k = lambda p_k / (c_k - mu), lambda =
    # g(mu) - mu, at the best mu and (normalised) at the root, and p restricted to the
    # cheapest actions pulled back into the ball (the limit mu -> min c, where the minimum is
    # only approached)
    members = []
    d = c[on] - mu
    if (d > 0).all():  # at the best mu, the rest of the mass on the cheapest action
        q = np.zeros_like(p)
        q[on] = (lower - mu) * p[on] / d
        q[np.argmin(c)] += max(1.0 - q.sum(), 0.0)
        members.append(q)
    if d_root is not None:
        q = np.zeros_like(p)
        q[on] = p[on] / d_root[on]
        members.append(q / q.sum())
    cheapest = c <= top + 1e-15 * max(1.0, abs(top))
    q = np.where(cheapest, p, 0.0) if (p[cheapest] > 0).any() else cheapest.astype(float)
    members.append(q / q.sum())
    q = min((_into_ball(m, p, eps) for m in members), key=lambda v: float(c @ v))
    return lower, float(c @ q), q, mu


def _minimax_lp(r: np.ndarray) -> np.ndarray:
    """``argmax_pi min_k (R^T pi)_k`` by an LP."""
    n_i, n_j = r.shape
    res = linprog(
        np.r_[np.zeros(n_i), -1.0],
        A_ub=np.c_[-r.T, np.ones(n_j)],
        b_ub=np.zeros(n_j),
        A_eq=np.r_[np.ones(n_i), 0.0][None],
        b_eq=[1.0],
        bounds=[(0.0, None)] * n_i + [(None, None)],
    )
    assert res.status == 0, res.message
    pi = np.clip(res.x[:n_i], 0.0, None)
    return pi / pi.sum()


def _simplex_constraint(n: int, extra: int) -> dict:
    return {
        "type": "eq",
        "fun": lambda x: x[:n].sum() - 1.0,
        "jac": lambda x: np.r_[np.ones(n), np.zeros(extra)],
    }


def _joint_g(r: np.ndarray, p: np.ndarray, eps: float, x: np.ndarray) -> tuple[float, np.ndarray]:
    """``g(pi, mu)`` at ``x = (pi, mu)`` and its gradient (jointly concave)."""
    n_i, on = r.shape[0], p > 0
    pi, mu = x[:n_i], x[n_i]
    d = r.T[on] @ pi - mu
    if (d <= 0).any():
        return mu, np.r_[np.zeros(n_i), 1.0]
    lam = math.exp(-eps + float(p[on] @ np.log(d)))
    gd = lam * p[on] / d
    return mu + lam, np.r_[r[:, on] @ gd, 1.0 - gd.sum()]


@dataclass
class Reference:
    strategy: np.ndarray  # pi_L
    opponent: np.ndarray  # q_U, a member of the ball
    lower: float  # L = phi(pi_L) (certified lower bound)
    upper: float  # U = max_i (R q_U)_i (certified upper bound)
    mu: float  # the dual variable at pi_L


def reference(r: np.ndarray, p: np.ndarray, eps: float) -> Reference:
    """Certified bracket ``[L, U]`` of Problem (38) and the strategy attaining ``L``."""
    r, p = np.asarray(r, dtype=float), np.asarray(p, dtype=float)
    n_i, n_j = r.shape
    if eps == 0.0:  # best response to p
        g = r @ p
        pi = (g >= g.max() - _ROUND).astype(float)
        return Reference(pi / pi.sum(), p.copy(), float(g.max()), float(g.max()), -math.inf)
    if math.isinf(eps):  # minimax, both sides by LP
        pi, q = _minimax_lp(r), _minimax_lp(-r.T)
        return Reference(pi, q, float((r.T @ pi).min()), float((r @ q).max()), -math.inf)
    on = p > 0
    sup, free = np.flatnonzero(on), np.flatnonzero(~on)
    ns, neg_entropy = sup.size, float(p[on] @ np.log(p[on]))

    def lower_joint() -> np.ndarray:
        """L jointly over ``(pi, mu)``: smooth, handles phi's kinks (one observed action)."""
        pi0 = np.full(n_i, 1.0 / n_i)
        x0 = np.r_[pi0, (r.T @ pi0).min() - max(1.0, float(np.ptp(r)))]
        res = minimize(
            lambda x: tuple(-v for v in _joint_g(r, p, eps, x)),
            x0,
            jac=True,
            method="SLSQP",
            bounds=[(0.0, 1.0)] * n_i + [(None, None)],
            constraints=[
                _simplex_constraint(n_i, 1),
                {
                    "type": "ineq",
                    "fun": lambda x: r.T @ x[:n_i] - x[n_i],
                    "jac": lambda x: np.c_[r.T, -np.ones(n_j)],
                },
            ],
            options=_SLSQP,
        )
        return res.x[:n_i]

    def lower_nested() -> np.ndarray:
        """L on phi itself, whose super-gradient is ``R q*(pi)`` (Danskin): robust where the
        joint problem's domain boundary trips SLSQP."""

        def neg_phi(pi: np.ndarray) -> tuple[float, np.ndarray]:
            pi = np.clip(pi, 0.0, None) / np.clip(pi, 0.0, None).sum()
            low, _, q = _worst(r.T @ pi, p, eps)
            return -low, -(r @ q)

        res = minimize(
            neg_phi,
            _minimax_lp(r),
            jac=True,
            method="SLSQP",
            bounds=[(0.0, 1.0)] * n_i,
            constraints=[_simplex_constraint(n_i, 0)],
            options=_SLSQP,
        )
        return res.x

    def unpack(y: np.ndarray) -> np.ndarray:
        q = np.zeros(n_j)
        q[sup], q[free] = np.exp(y[:ns]), y[ns:n_j]
        return q

    def dq(y: np.ndarray) -> np.ndarray:
        jac = np.zeros((n_j, n_j))
        jac[sup, np.arange(ns)] = np.exp(y[:ns])
        jac[free, ns + np.arange(free.size)] = 1.0
        return jac

    def upper_from(q0: np.ndarray) -> np.ndarray:
        """U: ``min_{q in Omega, t} t  s.t.  R q <= t``, ``q_k = exp(y_k)`` on the support."""
        q0 = 0.999 * q0 + 0.001 * p  # strictly positive on the support
        res = minimize(
            lambda y: (y[n_j], np.r_[np.zeros(n_j), 1.0]),
            np.r_[np.log(q0[sup]), q0[free], (r @ q0).max()],
            jac=True,
            method="SLSQP",
            bounds=[(None, 0.0)] * ns + [(0.0, 1.0)] * free.size + [(None, None)],
            constraints=[
                {
                    "type": "eq",
                    "fun": lambda y: unpack(y).sum() - 1.0,
                    "jac": lambda y: np.r_[dq(y).sum(0), 0.0],
                },
                {
                    "type": "ineq",
                    "fun": lambda y: y[n_j] - r @ unpack(y),
                    "jac": lambda y: np.c_[-r @ dq(y), np.ones(n_i)],
                },
                {  # eps - KL(p || q) = eps - sum p ln p + sum_{support} p_k y_k >= 0
                    "type": "ineq",
                    "fun": lambda y: eps - neg_entropy + p[sup] @ y[:ns],
                    "jac": lambda y: np.r_[p[sup], np.zeros(n_j - ns + 1)],
                },
            ],
            options=_SLSQP,
        )
        return _into_ball(unpack(res.x), p, eps)

    lower, upper = -math.inf, math.inf
    target = 0.1 * _REF_GAP * max(float(np.ptp(r)), 1.0)
    # the second round only when the first leaves a gap (SLSQP sometimes stalls)
    for find_pi, q_start in ((lower_joint, None), (lower_nested, p)):
        pi = np.clip(find_pi(), 0.0, None)
        pi = pi / pi.sum()
        low, _, q, mu = _inner(r.T @ pi, p, eps)
        if low > lower:
            pi_l, lower, mu_l = pi, low, mu
        # phi's worst opponent at pi is a member too, and the start of the U problem
        for member in (q, upper_from(q if q_start is None else q_start)):
            if (r @ member).max() < upper:
                upper, q_u = float((r @ member).max()), member
        if upper - lower <= target:
            break
    else:
        # where SLSQP's path depends on rounding (OpenBLAS with 2 threads, seed 16) the U
        # problem can stall at a gap of 1e-7 from either start: restart it from its best member
        for _ in range(2):
            member = upper_from(q_u)
            if (r @ member).max() < upper:
                upper, q_u = float((r @ member).max()), member
            if upper - lower <= target:
                break
    return Reference(pi_l, q_u, lower, upper, mu_l)


def near_optimal_box(
    r: np.ndarray, p: np.ndarray, eps: float, ref: Reference, level: float
) -> np.ndarray:
    """``[Ai, 2]``: bounds on each ``pi_i`` over ``{pi : phi(pi) >= level}``, by LP.

    Every member ``q`` of the ball gives ``pi^T R q >= phi(pi)``, so the polytope
    ``{pi : pi^T R q_l >= level for all l}`` contains that set whatever members ``q_l`` are
    used; its box (two LPs per action) is therefore a certified outer bound. The members are the
    worst opponents at points around ``pi_L`` at three distances (for finite positive ``eps``),
    whose cuts are the tangent planes of phi there: tight around a smooth maximum and at a kink.
    """
    n_i, n_j = r.shape
    if eps == 0.0:
        members = [p]
    elif math.isinf(eps):
        members = list(np.eye(n_j))
    else:
        members = [ref.opponent, _worst(r.T @ ref.strategy, p, eps)[2]]
        for h in (1e-2, 1e-3, 1e-4):
            for i in range(n_i):
                for j in range(n_i):
                    if i != j:
                        pi = ref.strategy + h * (np.eye(n_i)[i] - np.eye(n_i)[j])
                        members.append(_worst(r.T @ pi, p, eps)[2])
    cuts = -(r @ np.stack(members, axis=1)).T  # [L, Ai]: -pi^T R q_l <= -level
    box = np.empty((n_i, 2))
    for i in range(n_i):
        for side, sign in ((0, 1.0), (1, -1.0)):
            res = linprog(
                sign * np.eye(n_i)[i],
                A_ub=cuts,
                b_ub=np.full(len(members), -level),
                A_eq=np.ones((1, n_i)),
                b_eq=[1.0],
                bounds=[(0.0, 1.0)] * n_i,
                options=_LP_TIGHT,
            )
            assert res.status == 0, res.message
            box[i, side] = res.x[i]
    return box


# ---------------------------------------------------------------- the comparison


def _compare(
    reward: np.ndarray,
    center: object = None,
    radius: float | None = None,
    *,
    counts: np.ndarray | None = None,
    delta: float | None = None,
    responder_tols: tuple[float, ...] = (1e-8,),
) -> dict:
    """Check both toolkit solvers against the reference on one problem.

    The model is either ``counts`` and ``delta`` (the reference forms the ball itself) or
    ``center`` and ``radius``. :func:`solve_delta_safe` runs at ``tol=1e-9``, a fresh
    :class:`DeltaSafeResponder` at each of ``responder_tols`` (relative to the reward range);
    strategies are compared for the solvers certified to ``1e-6`` or better.

    Returns:
        A summary: the reference, the responses, and whether the optimum is certified unique.
    """
    r = np.asarray(reward, dtype=float)
    if counts is not None:
        counts = np.asarray(counts)
        center, radius = _ball(counts, delta, 1)
    p, eps = np.asarray(center, dtype=float), float(radius)
    spread = max(float(np.ptp(r)), 1.0)  # the toolkit's tolerances are relative to ptp(R)
    rounding = _ROUND * spread
    ref = reference(r, p, eps)
    ref_gap = max(ref.upper - ref.lower, 0.0)
    assert ref_gap <= _REF_GAP * spread, "the reference did not close its gap"
    # Problem (38) is never below the safety level of minimax (Omega is in the simplex)
    assert ref.upper >= float((r.T @ _minimax_lp(r)).min()) - rounding

    responses = []  # (name, response, certified gap it claims)
    ball = KLBall(p, eps)
    if counts is not None:
        responses.append(("exact", solve_delta_safe(r, counts, delta, tol=1e-9), 1e-9))
    else:
        responses.append(("exact", solve_delta_safe(r, ball=ball, tol=1e-9), 1e-9))
    for tol in responder_tols:
        responder = DeltaSafeResponder(r, tol=tol)
        res = responder.respond(counts, delta) if counts is not None else responder.respond_to(ball)
        responses.append((f"fast(tol={tol:g})", res, tol * spread))
    for name, res, own_gap in responses:
        pi = np.asarray(res.strategy, dtype=float)
        assert pi.min() >= -1e-12 and abs(pi.sum() - 1.0) <= 1e-9, name
        # (1) the reported value is phi(pi), checked by the independent inner bracket
        low, up, _ = _worst(r.T @ pi, p, eps)
        assert up - low <= 1e-9 * spread, name
        assert low - 1e-11 * spread <= res.value <= up + 1e-11 * spread, (name, low, res.value, up)
        # (2) the reported worst opponent is in the ball (our KL) and attains the value (to
        # rounding: the toolkit's Newton stops at |KL - eps| ~ 1e-15 or on a bracket of relative
        # width 1e-13; a KL excess moves the value by the KL multiplier times it, checked in (1))
        q = np.asarray(res.opponent, dtype=float)
        assert abs(q.sum() - 1.0) <= 1e-9 and q.min() >= -1e-12, name
        assert _ref_kl(p, q) <= eps + 1e-13 * max(1.0, eps), (name, _ref_kl(p, q) - eps)
        assert float(pi @ r @ q) == pytest.approx(res.value, abs=1e-9 * spread), name
        # (3) the value is optimal to the claimed gap: V in [L, U], and the toolkit's
        # certificate upper_bound is a true upper bound on V
        assert ref.lower - own_gap - ref_gap - rounding <= res.value, (name, res.value, ref)
        assert res.value <= ref.upper + rounding, (name, res.value, ref)
        assert res.upper_bound >= ref.lower - rounding, (name, res.upper_bound, ref)
        assert res.upper_bound - res.value <= own_gap + rounding, name
    # (4) strategies: all lie in the set of strategies within eta of the optimum (an outer box
    # of it); where that box is narrow the optimum is unique and they must agree with pi_L to
    # its width. eta reaches 1e-9 below the lowest value, which HiGHS needs to see the cuts
    # feasible.
    tight = [(name, res) for name, res, gap in responses if gap <= 1e-6 * spread]
    eta = max(ref.upper - min(res.value for _, res in tight), 0.0) + 1e-9 * spread
    box = near_optimal_box(r, p, eps, ref, ref.upper - eta)
    slack = 1e-8  # HiGHS's feasibility tolerance (1e-10) times the cut norms, with margin
    width = float((box[:, 1] - box[:, 0]).max()) + 2 * slack
    unique = width <= 1e-2
    for name, res in tight:
        pi = np.asarray(res.strategy, dtype=float)
        assert np.all(pi >= box[:, 0] - slack) and np.all(pi <= box[:, 1] + slack), name
        if unique:
            np.testing.assert_allclose(pi, ref.strategy, rtol=0, atol=width, err_msg=name)
            # and so does the expected payoff under the model's centre, pi^T R p
            assert abs((pi - ref.strategy) @ r @ p) <= width * np.abs(r @ p).sum(), name
    return {"ref": ref, "unique": unique, **{name: res for name, res, _ in responses}}


# ---------------------------------------------------------------- the cases


def test_reference_brackets_known_solutions() -> None:
    # sanity of the reference itself, where Problem (38) has a closed form
    # RPS with no information: minimax, value 0, uniform strategy
    ref = reference(RPS_REWARD, np.full(3, 1 / 3), math.inf)
    assert ref.lower == pytest.approx(0.0, abs=1e-12) and ref.upper == pytest.approx(0.0)
    np.testing.assert_allclose(ref.strategy, np.full(3, 1 / 3), atol=1e-9)
    # a single observed action a: q_a >= e^-eps, the rest on the cheapest action, so against
    # constant-row R the value is e^-eps R_a + (1 - e^-eps) min R for the best row
    r = np.array([[1.0, 0.0], [0.6, 0.5]])
    eps = 0.4
    w = math.exp(-eps)
    ref = reference(r, np.array([1.0, 0.0]), eps)
    expected = max(w * 1.0 + (1 - w) * 0.0, w * 0.6 + (1 - w) * 0.5, 0.5)
    assert ref.lower == pytest.approx(expected, abs=1e-9) and ref.upper == pytest.approx(expected)
    # a point ball: the best response to the centre
    ref = reference(RPS_REWARD, np.array([0.6, 0.2, 0.2]), 0.0)
    np.testing.assert_allclose(ref.strategy, [0, 1, 0])
    assert ref.lower == pytest.approx(0.4)
    # the inner bracket against a vertex formula: c flat on the support
    low, up, q = _worst(np.array([1.0, 1.0, -2.0]), np.array([0.5, 0.5, 0.0]), 0.3)
    assert low == pytest.approx(math.exp(-0.3) - 2 * (1 - math.exp(-0.3)), abs=1e-10)
    assert up - low <= 1e-10
    # the radius matches the toolkit's (Sec. 5.2.1 formula, union bound of Sec. 5.3)
    for n, a, s in [(1, 3, 1), (37, 3, 1), (10**6, 5, 10)]:
        assert kl_bound(0.1, n, a, s) == pytest.approx(_ref_radius(0.1, n, a, s), rel=1e-14)


RPS_MODELS = {
    "rock-heavy": (30, 10, 10),  # Fig. 5.1's (0.6, 0.2, 0.2), 50 games
    "paper-lean": (8, 14, 10),
    "near-uniform": (34, 33, 33),
    "unseen-scissors": (9, 3, 0),
    "one-action": (5, 0, 0),
    "large-sample": (6000, 2000, 2000),
}


@pytest.mark.parametrize("delta", [0.01, 0.1, 0.5, 0.95])
@pytest.mark.parametrize("model", list(RPS_MODELS))
def test_rock_paper_scissors(model: str, delta: float) -> None:
    counts = np.array(RPS_MODELS[model])
    summary = _compare(RPS_REWARD, counts=counts, delta=delta)
    if model == "near-uniform":  # the ball holds the uniform opponent: nothing beats minimax
        assert summary["ref"].upper == pytest.approx(0.0, abs=1e-9)
        np.testing.assert_allclose(summary["exact"].strategy, np.full(3, 1 / 3), atol=1e-4)


SERVE_MODELS = {  # the simulated volunteers of Sec. 5.4.2 (forehand side, middle, backhand side)
    "uniform": (1 / 3, 1 / 3, 1 / 3),
    "forehand-side": (0.7, 0.2, 0.1),
    "switching-before": (0.8, 0.15, 0.05),
    "switching-after": (0.05, 0.45, 0.5),
}


@pytest.mark.parametrize("volunteer", list(SERVE_MODELS))
def test_table_tennis_serves(volunteer: str) -> None:
    # the block sizes the serve experiment sees (n_min = 20 and its multiples), delta = 0.1 as
    # there, and the responder's default tolerance as the AdaptiveLearner uses it
    rng = np.random.default_rng(sum(map(ord, volunteer)))
    for n, delta in [(1, 0.1), (20, 0.1), (60, 0.1), (150, 0.1), (40, 0.01), (40, 0.5)]:
        counts = rng.multinomial(n, SERVE_MODELS[volunteer])
        _compare(TABLE_TENNIS_REWARD, counts=counts, delta=delta, responder_tols=(1e-8, 1e-4))


def test_serve_stream_with_warm_start() -> None:
    # the online use: one responder warm-started along a stream of serves, every answer checked
    rng = np.random.default_rng(21)
    responder = DeltaSafeResponder(TABLE_TENNIS_REWARD)  # default tol, as in the experiments
    spread = float(np.ptp(TABLE_TENNIS_REWARD))
    counts = np.zeros(3, dtype=int)
    for t in range(40):
        counts[rng.choice(3, p=SERVE_MODELS["forehand-side"] if t < 25 else (0.1, 0.3, 0.6))] += 1
        res = responder.respond(counts, 0.1)
        p, eps = _ball(counts, 0.1, 1)
        low, up, _ = _worst(TABLE_TENNIS_REWARD.T @ res.strategy, p, eps)
        assert low - 1e-10 <= res.value <= up + 1e-10
        if t % 4 == 3:
            ref = reference(TABLE_TENNIS_REWARD, p, eps)
            assert ref.lower - 1e-4 * spread - 1e-9 <= res.value <= ref.upper + _ROUND


def _random_instance(seed: int) -> tuple[np.ndarray, np.ndarray, float]:
    rng = np.random.default_rng(seed)
    n_i, n_j = (int(v) for v in rng.integers(3, 6, size=2))
    reward = rng.normal(size=(n_i, n_j))
    if seed % 4 == 1:  # integer payoffs: ties between actions
        reward = rng.integers(-2, 3, size=(n_i, n_j)).astype(float)
    alpha = np.ones(n_j) if seed % 3 else np.full(n_j, 0.3)  # sparse counts: unseen actions
    counts = rng.multinomial(int(10 ** rng.uniform(0.5, 3.5)), rng.dirichlet(alpha))
    return reward, counts, float(rng.choice([0.01, 0.1, 0.5]))


@functools.cache
def _random_game_summary(seed: int) -> dict:
    reward, counts, delta = _random_instance(seed)
    return _compare(reward, counts=counts, delta=delta)


@pytest.mark.parametrize("seed", range(24))
def test_random_small_games(seed: int) -> None:
    _random_game_summary(seed)


def test_random_games_mostly_have_unique_optima() -> None:
    # the strategy comparison must not be vacuous: most random games have a certified unique
    # optimum (cached from test_random_small_games when run in the same session)
    unique = [_random_game_summary(seed)["unique"] for seed in range(24)]
    assert sum(unique) >= 20


_DUPLICATE_ROWS = [[1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 0.5, -0.5]]
_DUPLICATE_COLUMNS = [[1.0, 1.0, -1.0], [-1.0, -1.0, 1.0], [0.2, 0.2, 0.0]]
_DOMINATED_ROW = [[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [-1.0, -1.0, -1.0]]
EDGE_CASES = {
    # radius 0: the model is the empirical distribution, (38) is fictitious play
    "radius-0": (RPS_REWARD, (0.5, 0.3, 0.2), 0.0),
    "radius-1e-6": (RPS_REWARD, (0.5, 0.3, 0.2), 1e-6),
    # radius inf (no data, delta -> 0): the ball is the simplex, (38) is the minimax LP
    "radius-inf": (TABLE_TENNIS_REWARD, (1 / 3, 1 / 3, 1 / 3), math.inf),
    # so large a radius that the ball is the simplex up to e^-50: minimax again
    "radius-50": (TABLE_TENNIS_REWARD, (0.6, 0.3, 0.1), 50.0),
    "radius-50-rps": (RPS_REWARD, (0.6, 0.3, 0.1), 50.0),
    # ties and degeneracy
    "constant-reward": (np.zeros((3, 3)), (0.5, 0.3, 0.2), 0.2),
    "duplicate-rows": (_DUPLICATE_ROWS, (0.4, 0.4, 0.2), 0.1),
    "duplicate-columns": (_DUPLICATE_COLUMNS, (0.3, 0.3, 0.4), 0.05),
    "dominated-row": (_DOMINATED_ROW, (0.5, 0.5, 0.0), 0.2),
    "flat-on-support": (np.array([[1.0, 1.0, -2.0], [0.0, 0.0, 0.0]]), (0.5, 0.5, 0.0), 0.3),
    "tied-best-responses": (RPS_REWARD, (0.5, 0.5, 0.0), 0.05),
    "single-column": (np.array([[0.3], [0.7], [0.7]]), (1.0,), 0.5),
    "single-row": (np.array([[0.3, -0.2, 0.9]]), (0.2, 0.3, 0.5), 0.5),
}


@pytest.mark.parametrize("case", list(EDGE_CASES))
def test_edge_cases(case: str) -> None:
    reward, center, radius = EDGE_CASES[case]
    summary = _compare(np.asarray(reward), center, radius)
    ref = summary["ref"]
    if case.startswith("radius-inf") or case.startswith("radius-50"):
        r = np.asarray(reward)
        assert ref.upper == pytest.approx(float((r.T @ _minimax_lp(r)).min()), abs=1e-9)
    if case == "radius-0":
        assert ref.upper == pytest.approx(float((np.asarray(reward) @ center).max()))
    if case in ("constant-reward", "duplicate-rows", "single-column"):
        assert summary["unique"] is False  # ties are seen as ties, not compared as strategies


def test_delta_limits() -> None:
    counts = np.array([30, 15, 5])
    # delta = 0 is no model at all (eps = inf); the toolkit rejects it, and tiny delta goes to
    # the minimax solution
    with pytest.raises(ValueError, match="delta"):
        DeltaSafeResponder(TABLE_TENNIS_REWARD).respond(counts, 0.0)
    for delta in (1e-12, 1e-300):
        _compare(TABLE_TENNIS_REWARD, counts=counts, delta=delta)
    # no observations: the whole simplex whatever delta
    _compare(RPS_REWARD, counts=np.zeros(3, dtype=int), delta=0.3)
    # delta -> 1: the smallest ball the data allow, eps = (|Aj| - 1) ln(N + 1) / N
    _compare(RPS_REWARD, counts=counts, delta=1 - 1e-12)


def test_two_stage_tree_against_reference_backward_induction() -> None:
    # Sec. 5.3 on two-stage RPS (Fig. 5.3): the toolkit's delta-safe backward induction against
    # our own, with the per-state radius eps(delta / |S|, N_s) and continuation matrices
    # R^s + V(child) built here from the game's definition
    rng = np.random.default_rng(8)
    table_5_2 = [(0.6, 0.2, 0.2), (0.2, 0.6, 0.2), (0.4, 0.4, 0.2), (0.2, 0.4, 0.4)]
    counts = [rng.multinomial(int(rng.integers(0, 200)), table_5_2[s % 4]) for s in range(10)]
    counts[4] = np.zeros(3, dtype=int)  # a never-visited state: its ball is the simplex
    delta, n_states = 0.1, 10
    values = np.zeros(n_states)
    errors = np.zeros(n_states)  # certified bound on |V_toolkit - V_ours| at each state
    for s in range(1, 10):  # leaves: 2 x RPS
        ref = reference(2 * RPS_REWARD, *_ball(counts[s], delta, n_states))
        values[s], errors[s] = ref.lower, ref.upper - ref.lower
    root = RPS_REWARD + values[1:].reshape(3, 3)  # state 1 + 3 a_i + a_j follows (a_i, a_j)
    ref = reference(root, *_ball(counts[0], delta, n_states))
    # V is 1-Lipschitz in the matrix's entries (sup norm): child errors add up at the root
    root_err = ref.upper - ref.lower + errors[1:].max()
    for method, tol in (("exact", 1e-9), ("subgradient", 1e-8)):
        res = delta_safe_tree(two_stage_rps(), counts, delta, method=method, tol=tol)
        slack = tol * 8 + 1e-9  # the solvers' certified gaps, relative to ptp(R^s) <= 8
        np.testing.assert_allclose(res.values[1:], values[1:], atol=slack + errors[1:].max())
        assert res.values[0] == pytest.approx(ref.lower, abs=root_err + 2 * slack)


def test_regression_worst_opponent_inside_tiny_ball() -> None:
    # Regression (found by this reference): the inner Newton iteration stopped at
    # |KL(p || q) - eps| < 1e-13, so a warm-started worst opponent could lie up to ~1e-13
    # outside the ball in KL. The value moves by the KL multiplier times that excess, ~500 at
    # eps = 1e-6: the responder reported value = upper_bound = 0.29889516244526 for the pure
    # strategy "paper", 5.4e-11 below both phi(paper) and the optimum V = 0.29889516249..., so
    # its "certified" upper bound was below the optimum it certifies.
    p, eps = np.array([0.5, 0.3, 0.2]), 1e-6
    ref = reference(RPS_REWARD, p, eps)
    res = DeltaSafeResponder(RPS_REWARD).respond_to(KLBall(p, eps))
    assert _ref_kl(p, res.opponent) <= eps + 1e-15
    low, up, _ = _worst(RPS_REWARD.T @ res.strategy, p, eps)
    assert low - 1e-12 <= res.value <= up + 1e-12
    assert res.upper_bound >= ref.lower - 1e-12


def _ball(counts: np.ndarray, delta: float, n_states: int) -> tuple[np.ndarray, float]:
    n = int(counts.sum())
    center = counts / n if n else np.full(counts.size, 1 / counts.size)
    return center, _ref_radius(delta, n, counts.size, n_states)
