"""Part selection: the candidates whose description E(X) is shortest
(paper section 3.5, Eqs. 6-7).

For n candidate parts with explained-pixel masks e_i and commission masks c_i:

* ``M_a[i, i] = |e_i|``, ``M_a[i, j] = -|e_i ∩ e_j| / 2``; ``M_c`` likewise for c_i. With
  no pixel in three parts, X M_a X^T is exactly the number of pixels the chosen parts
  explain, X M_c X^T the number of commission pixels.
* ``E(X) = κ0 |X| + κ1 X M_a X^T + κ2 X M_c X^T + κ3 (N - X M_a X^T)`` (Eq. 6), with the
  costs derived from :class:`~sqparts.Encoding`:

  - κ0 = bits of one part (14 parameters × ``bits_per_parameter``, by default ½ log2 N
    each: see :func:`~sqparts.encoding_for`);
  - κ1 = log2(σ/q), bits of a pixel explained within ±σ/2;
  - κ2 = λ (b - κ1), bits of a commission error (Eq. 5's definition of λ);
  - κ3 = b = log2(D/q), bits of a pixel left unexplained (sent raw);
  - N = number of figure pixels.

Selection minimises E over binary X: :func:`select_best_first` (the paper's iterative
best-first search: add the part that lowers E most, drop any part whose removal
lowers E, until neither helps), :func:`select_tabu` (from there, tabu search over flips
and swaps: recovery's default) and :func:`select_exact` (the integer-programming route:
the quadratic is linearised with y_ij = x_i x_j and solved to optimality by HiGHS, group
by group of interacting candidates). The choice is then corrected on E counted in the
candidates' joint rendering (:func:`select_rendered`). The costs and E themselves are
:mod:`sqparts._encoding`'s.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import os
import sys
import time

import numpy as np

from ._data import RangeData
from ._encoding import Costs, area_matrix, layer_counts


@dataclasses.dataclass(frozen=True)
class SelectionProblem:
    """Eq. (6) for a set of candidates: ``E(X) = linear·X + X^T Q X + constant`` where
    ``Q`` has zero diagonal (x_i² = x_i is folded into ``linear``)."""

    area: np.ndarray  # M_a
    commission: np.ndarray  # M_c
    costs: Costs

    @classmethod
    def from_masks(cls, explained, commission, costs: Costs) -> "SelectionProblem":
        return cls(area_matrix(explained), area_matrix(commission), costs)

    @property
    def size(self) -> int:
        return len(self.area)

    @property
    def combined(self) -> np.ndarray:
        """M of Eq. (7) without the κ0 I term: (κ1 - κ3) M_a + κ2 M_c."""
        c = self.costs
        return (c.explained - c.omission) * self.area + c.commission * self.commission

    @property
    def linear(self) -> np.ndarray:
        return self.costs.part + np.diag(self.combined)

    @property
    def pairwise(self) -> np.ndarray:
        q = self.combined.copy()
        np.fill_diagonal(q, 0.0)
        return q

    @property
    def constant(self) -> float:
        return self.costs.omission * self.costs.figure_pixels

    def groups(self) -> list[np.ndarray]:
        """The candidates' index sets that interact (connected by nonzero pairwise terms),
        smallest first: E(X) is the constant plus a sum over them."""
        from scipy.sparse.csgraph import connected_components

        if self.size == 0:
            return []
        count, labels = connected_components(np.abs(self.pairwise) > 1e-12, directed=False)
        groups = [np.flatnonzero(labels == k) for k in range(count)]
        return sorted(groups, key=len)

    def subproblem(self, index) -> "SelectionProblem":
        """The candidates ``index`` alone (the same costs)."""
        index = np.asarray(index)
        return SelectionProblem(self.area[np.ix_(index, index)], self.commission[np.ix_(index, index)], self.costs)

    def energy(self, x) -> float:
        """E(X), Eq. (6), in bits."""
        x = np.asarray(x, np.float64)
        c = self.costs
        xa = x @ self.area @ x
        return float(
            c.part * x.sum()
            + c.explained * xa
            + c.commission * (x @ self.commission @ x)
            + c.omission * (c.figure_pixels - xa)
        )


def select_best_first(problem: SelectionProblem, *, max_iter: int | None = None) -> np.ndarray:
    """The paper's iterative best-first search: starting from no parts, flip the single
    part (add or drop) that lowers E(X) most, until no flip lowers it (or after
    ``max_iter`` flips, default 4n + 10). Returns a bool array. On the host: each step
    is one pass over n numbers (n at most a few hundred), where a compiled program would
    cost more to build than all its calls in a recovery."""
    n = problem.size
    x = np.zeros(n, bool)
    if n == 0:
        return x
    pair = 2.0 * problem.pairwise
    field = problem.linear.astype(np.float64)  # E's change on adding each part (while it is out)
    for _ in range(4 * n + 10 if max_iter is None else max_iter):
        change = np.where(x, -field, field)
        i = int(np.argmin(change))
        if not change[i] < -1e-9:
            break
        x[i] = not x[i]
        field += pair[:, i] if x[i] else -pair[:, i]
    return x


TABU_MOVES = 10
"""Moves of :func:`select_tabu` per candidate of a group."""

TABU_TENURE = 7
"""Moves for which :func:`select_tabu` leaves a flipped candidate alone (at most a third
of the group's candidates)."""


def select_tabu(problem: SelectionProblem) -> np.ndarray:
    """E(X) minimised by tabu search over single flips and swaps, group by group of
    interacting candidates (:meth:`SelectionProblem.groups`), each from its best-first
    selection (:func:`select_best_first`): every move is the flip (add or drop one
    candidate) or the swap (drop one, add another) that lowers E most or raises it
    least, except that a candidate flipped in the last :data:`TABU_TENURE` moves is left
    alone unless moving it gives the lowest E yet; :data:`TABU_MOVES` moves per
    candidate, and the lowest E met is returned (bool (n,)), never higher than
    best-first's.

    Best-first stops where no single flip helps. Where several candidates explain the
    same pixels, the better one is reached from a worse one only through a swap, or
    through a dearer selection on the way (dropping it first, or adding the other on
    top): the swaps and the tabu memory take those steps. On the problems recoveries
    meet it mostly ends where the integer program proves the optimum
    (``benchmarks/bench_select.py``), in milliseconds where the proof can take seconds
    (the pairwise linearisation bounds the overlaps weakly), but it proves nothing. A
    lone candidate is chosen when it lowers E by itself."""
    return _by_groups(problem, lambda sub: _tabu_group(sub.linear, 2.0 * sub.pairwise, select_best_first(sub)))


def _by_groups(problem: SelectionProblem, solve) -> np.ndarray:
    """The bool selection of each group of interacting candidates
    (:meth:`SelectionProblem.groups`) by ``solve(subproblem)``: E is the constant plus a
    sum over the groups. A lone candidate is chosen when it lowers E by itself."""
    x = np.zeros(problem.size, bool)
    linear = problem.linear
    for group in problem.groups():
        x[group] = linear[group] < 0.0 if len(group) == 1 else solve(problem.subproblem(group))
    return x


def _tabu_group(linear: np.ndarray, pair: np.ndarray, start: np.ndarray) -> np.ndarray:
    """:func:`select_tabu` on one group: E(x) = linear·x + Σ_{i<j} pair_ij x_i x_j
    (``pair`` symmetric, zero diagonal), from the bool selection ``start``."""
    n = len(linear)
    tenure = min(TABU_TENURE, n // 3)
    x = start.astype(np.float64)
    field = linear + pair @ x  # E's change on adding each candidate (while it is out)
    e = float(linear @ x + 0.5 * x @ pair @ x)
    best_e, best = e, x.copy()
    last = np.full(n, -(tenure + 1))  # the move at which each candidate last flipped
    for move in range(TABU_MOVES * n):
        on = x > 0
        free = move - last > tenure
        flip = np.where(on, -field, field)
        swap = np.where(on[:, None] & ~on[None, :], field[None, :] - field[:, None] - pair, np.inf)  # i out, j in
        flip = np.where(free | (e + flip < best_e - 1e-9), flip, np.inf)
        swap = np.where((free[:, None] & free[None, :]) | (e + swap < best_e - 1e-9), swap, np.inf)
        i, k = int(np.argmin(flip)), int(np.argmin(swap))
        if not np.isfinite(min(flip[i], swap.flat[k])):
            break
        moved, change = ([i], flip[i]) if flip[i] <= swap.flat[k] else (list(divmod(k, n)), swap.flat[k])
        for m in moved:
            sign = 1.0 - 2.0 * x[m]
            x[m] += sign
            field += sign * pair[:, m]
            last[m] = move
        e += float(change)
        if e < best_e - 1e-9:
            best_e, best = e, x.copy()
    return best > 0.5


@contextlib.contextmanager
def _quiet_stdout():
    """Silence what C code writes to standard output (file descriptor 1), buffered or not.
    The descriptor is process-wide: keep what runs inside short (a constructor)."""
    if sys.stdout is not None:
        sys.stdout.flush()
    try:
        saved = os.dup(1)
    except OSError:  # no descriptor 1 at all
        yield
        return
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
        yield
    finally:
        _flush_c_stdio()
        os.dup2(saved, 1)
        os.close(saved)


def _flush_c_stdio():
    try:
        import ctypes

        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError, TypeError):  # no C library to ask (not POSIX)
        pass


NODE_LIMIT = 3000
"""Default most branch-and-bound nodes per group of interacting candidates. A bound on
work that, unlike seconds, stops HiGHS at the same incumbent on every machine."""


def select_exact(
    problem: SelectionProblem, *, time_limit: float = 30.0, node_limit: int | None = None
) -> tuple[np.ndarray, bool]:
    """Globally optimal X by integer programming (HiGHS). Returns (selection, proven_optimal).

    E is a sum over the groups of candidates that interact (a nonzero pairwise term,
    directly or through others: :meth:`SelectionProblem.groups`), so each group is solved
    alone, the smallest first, each with at most ``node_limit`` branch-and-bound nodes
    (None: no limit) and the time left of ``time_limit``; a lone candidate is chosen when
    it lowers E by itself. Stopped by the node limit, the selection is HiGHS's best so
    far, the same on every machine; stopped by the time limit, it depends on the
    machine's speed."""
    x, status = _select_exact(problem, time_limit, node_limit)
    return x, status == "exact"


def _select_exact(problem: SelectionProblem, time_limit: float, node_limit: int | None) -> tuple[np.ndarray, str]:
    """:func:`select_exact`, with how it ended: ``"exact"`` (proven optimal), ``"exact
    (node limit)"`` or ``"exact (time limit)"`` (the first limit any group reached)."""
    endings = []
    deadline = time.monotonic() + float(time_limit)

    def solve(sub):
        chosen, ended = _select_exact_group(sub, max(deadline - time.monotonic(), 0.05), node_limit)
        endings.append(ended)
        return chosen

    x = _by_groups(problem, solve)
    return x, next((e for e in endings if e != "exact"), "exact")


def _select_exact_group(
    problem: SelectionProblem, time_limit: float, node_limit: int | None = None
) -> tuple[np.ndarray, str]:
    """One group by HiGHS: E = linear·x + Σ_{i<j} 2 Q_ij y_ij + const with y_ij = x_i x_j
    enforced by y ≥ x_i + x_j - 1 where Q_ij > 0 and y ≤ x_i, y ≤ x_j where Q_ij < 0.
    Returns (selection, how it ended, as :func:`_select_exact`)."""
    import highspy

    n = problem.size
    if n == 0:
        return np.zeros(0, bool), "exact"
    q = problem.pairwise
    pairs = [(i, j) for i, j in zip(*np.triu_indices(n, 1)) if abs(q[i, j]) > 1e-12]

    def solve(start):
        with _quiet_stdout():  # highspy >= 1.16 prints a banner from its constructor
            h = highspy.Highs()
        h.setOptionValue("output_flag", False)
        h.setOptionValue("time_limit", float(time_limit))
        if node_limit is not None:
            h.setOptionValue("mip_max_nodes", int(node_limit))
        m = n + len(pairs)
        inf = highspy.kHighsInf
        h.addVars(m, np.zeros(m), np.ones(m))
        cost = np.concatenate([problem.linear, [2.0 * q[i, j] for i, j in pairs]])
        h.changeColsCost(m, np.arange(m, dtype=np.int32), cost)
        h.changeColsIntegrality(n, np.arange(n, dtype=np.int32), np.array([highspy.HighsVarType.kInteger] * n))
        for k, (i, j) in enumerate(pairs):
            y = n + k
            if q[i, j] > 0:  # y >= x_i + x_j - 1
                h.addRow(-1.0, inf, 3, np.array([y, i, j], np.int32), np.array([1.0, -1.0, -1.0]))
            else:  # y <= x_i, y <= x_j
                h.addRow(-inf, 0.0, 2, np.array([y, i], np.int32), np.array([1.0, -1.0]))
                h.addRow(-inf, 0.0, 2, np.array([y, j], np.int32), np.array([1.0, -1.0]))
        if start is not None:
            sol = highspy.HighsSolution()
            sol.col_value = list(np.concatenate([start, [start[i] * start[j] for i, j in pairs]]))
            h.setSolution(sol)
        h.run()
        values = np.asarray(h.getSolution().col_value[:n])
        if values.size != n:
            return None, "exact (time limit)", False
        x = values > 0.5
        model = h.getModelStatus()
        ended = (
            "exact"
            if model == highspy.HighsModelStatus.kOptimal
            else "exact (time limit)"
            if model == highspy.HighsModelStatus.kTimeLimit
            else "exact (node limit)"
        )
        # The returned columns must have the objective HiGHS reports: highspy 1.16
        # returns the start instead of its optimum after presolve.
        objective = h.getInfo().objective_function_value
        consistent = abs(problem.energy(x) - problem.constant - objective) <= 1e-6 * (1.0 + abs(objective))
        return x, ended, consistent

    # Start from the best-first selection: its E bounds the branch and bound at once.
    greedy = select_best_first(problem)
    x, ended, consistent = solve(greedy.astype(np.float64))
    if x is not None and not consistent:
        x, ended, consistent = solve(None)
    if x is None or not consistent:
        return greedy, ended if ended != "exact" else "exact (time limit)"
    return x, ended


def select_brute_force(problem: SelectionProblem) -> np.ndarray:
    """Exhaustive minimum of E(X) (reference for tests; n ≤ 16)."""
    n = problem.size
    if n > 16:
        raise ValueError(f"problem: got {n} candidates, expected at most 16 for brute force")
    best, best_x = np.inf, np.zeros(n, bool)
    for bits in itertools.product([0, 1], repeat=n):
        e = problem.energy(bits)
        if e < best - 1e-9:
            best, best_x = e, np.asarray(bits, bool)
    return best_x


METHODS = ("auto", "tabu", "exact", "best-first")
"""The ways :func:`select_parts` minimises E(X)."""


def select_parts(
    problem: SelectionProblem,
    *,
    method: str = "auto",
    exact_limit: int = 200,
    time_limit: float = 15.0,
    node_limit: int | None = NODE_LIMIT,
) -> tuple[np.ndarray, str]:
    """Choose parts: ``"tabu"`` (:func:`select_tabu`), ``"exact"``, ``"best-first"`` or
    ``"auto"`` (tabu search when the candidate count is at most ``exact_limit``, its
    work growing as the cube of a group's size; best-first beyond). ``"exact"``: HiGHS
    starts from the best-first selection and stops after ``node_limit``
    branch-and-bound nodes per group, or ``time_limit`` seconds in all, with the best
    selection it has found, reported as ``"exact (node limit)"`` or ``"exact (time
    limit)"``, never worse than best-first. Returns (selection, method used)."""
    if method not in METHODS:
        raise ValueError(f"method: got {method!r}, expected one of {', '.join(map(repr, METHODS))}")
    if method == "best-first" or (method == "auto" and problem.size > exact_limit):
        return select_best_first(problem), "best-first"
    if method in ("auto", "tabu"):
        return select_tabu(problem), "tabu"
    x, status = _select_exact(problem, time_limit, node_limit)
    if status == "exact":
        return x, status
    greedy = select_best_first(problem)
    return (greedy, "best-first") if problem.energy(greedy) < problem.energy(x) else (x, status)


@dataclasses.dataclass(frozen=True)
class SelectSettings:
    """How :func:`~sqparts.recover` chooses among the candidates (Eq. 7): ``method``
    ``"auto"``, ``"tabu"``, ``"exact"`` or ``"best-first"``, with ``exact_limit`` (the
    most candidates ``"auto"`` searches by tabu search; the name is kept from when it
    chose the integer program), ``node_limit`` and ``time_limit`` as for
    :func:`select_parts`: the node limit (None: none) bounds the integer program's work
    the same on every machine, so that a recovery's result does not depend on the
    machine's speed; the time limit only caps the wall time. The choice is then
    corrected on E counted in the candidates' joint rendering
    (:func:`~sqparts.select_rendered`)."""

    method: str = "auto"
    exact_limit: int = 200
    time_limit: float = 15.0
    node_limit: int | None = NODE_LIMIT

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"method: got {self.method!r}, expected one of {', '.join(map(repr, METHODS))}")
        if not (isinstance(self.exact_limit, int) and not isinstance(self.exact_limit, bool) and self.exact_limit >= 0):
            raise ValueError(f"exact_limit: got {self.exact_limit!r}, expected an integer >= 0")
        if isinstance(self.time_limit, bool) or not (
            isinstance(self.time_limit, (int, float)) and 0 < self.time_limit < float("inf")
        ):
            raise ValueError(f"time_limit: got {self.time_limit!r}, expected a finite number of seconds > 0")
        n = self.node_limit
        if n is not None and (isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1):
            raise ValueError(f"node_limit: got {n!r}, expected None or an integer >= 1")

    def select(self, problem: SelectionProblem) -> tuple[np.ndarray, str]:
        """:func:`select_parts` with these settings."""
        return select_parts(
            problem,
            method=self.method,
            exact_limit=self.exact_limit,
            time_limit=self.time_limit,
            node_limit=self.node_limit,
        )


def select_rendered(layers: np.ndarray, data: RangeData, costs: Costs, *, start=None, chunk: int = 32) -> np.ndarray:
    """Best-first selection on E counted in the joint rendering of the candidates' depth
    ``layers`` (n, H, W; :func:`render_layers`): a pixel explained by several parts counts
    once, a part hidden behind another explains nothing there. Eq. (7)'s area matrices
    count only pairwise overlaps: where many swollen candidates overlap they credit
    commission shared by k parts k(k-1)/2 times, and the quadratic optimum can be far
    from the true E. From ``start`` (a bool selection, e.g. the quadratic's) and from
    nothing, the single addition or removal that lowers E most is made until none does;
    the better end is returned (bool (n,))."""
    n = len(layers)
    empty = np.full(layers.shape[1:], np.inf, np.float32)
    best, best_e = None, np.inf
    seeds = [np.zeros(n, bool)] + ([np.asarray(start, bool).copy()] if start is not None else [])
    for x in seeds:
        while True:
            cur = layers[x].min(0) if x.any() else empty
            k = int(x.sum())
            e_now = costs.total(k, *layer_counts(cur, data))
            add = np.concatenate(
                [
                    costs.total(k + 1, *layer_counts(np.minimum(cur, layers[j : j + chunk]), data))
                    for j in range(0, n, chunk)
                ]
            )
            add[x] = np.inf
            on = np.flatnonzero(x)
            drop = np.array(
                [
                    costs.total(k - 1, *layer_counts(layers[np.delete(on, i)].min(0) if k > 1 else empty, data))
                    for i in range(k)
                ]
            )
            a = int(np.argmin(add))
            d = int(np.argmin(drop)) if k else -1
            if k and drop[d] <= add[a] and drop[d] < e_now - 1e-9:
                x[on[d]] = False
            elif add[a] < e_now - 1e-9:
                x[a] = True
            else:
                break
        if e_now < best_e:
            best, best_e = x, e_now
    assert best is not None  # E is finite, so the first seed always sets it
    return best
