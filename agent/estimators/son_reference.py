"""The solvers the default IPM is checked against, and the least-squares baseline.

* :class:`OsqpSolver` — (10) of García Carrillo et al. as the QP
  min ½‖w‖² + δ·1ᵀ(a + b)  s.t. Hx + w + a − b = z,  a, b ≥ 0
  (ℓ̄ = a − b; this is (10) scaled by λ²c² with the quadratic term carried by w = r − ℓ̄). The OSQP
  object is set up once per window *shape* (sparsity pattern) and afterwards only updated
  (``Ax``, ``l``, ``u``, ``q``).
* :class:`CvxpyReference` — the literal (10) in x and ℓ̄ (c = 1, λ = λ(δ)) with cvxpy + Clarabel, a
  DPP-parametrised problem compiled once per shape; the independent reference of the tests.
* :func:`solve_ls` — least squares (δ = ∞), the batched-least-squares baseline, by one banded solve
  (:func:`son_banded.ls_solve_all`).

All return the common :class:`son_problem.SolveOut` (:func:`son_problem.evaluate_solution`). The
quadratic rows of a problem (``lsq``: the arrival cost) get ℓ̄ᵢ = 0: OSQP bounds aᵢ = bᵢ = 0, cvxpy has
no ℓ̄ variable for them.
"""

from __future__ import annotations

import math
from collections import OrderedDict

import numpy as np

from .son_banded import ls_solve_all
from .son_problem import HuberProblem, SolveOut, evaluate_solution, lambda_from_delta

__all__ = ["CvxpyReference", "OsqpSolver", "solve_ls"]


def _lru_entry(cache: OrderedDict, size: int, key, setup) -> tuple[dict, bool]:
    """The solver set-up cached under ``key`` (made by ``setup()`` when absent, the least recently used one
    evicted beyond ``size``), and whether it was made now."""
    ent = cache.get(key)
    if ent is not None:
        cache.move_to_end(key)
        return ent, False
    ent = cache[key] = setup()
    if len(cache) > size:
        cache.popitem(last=False)
    return ent, True


def solve_ls(prob: HuberProblem) -> SolveOut:
    """Least squares on the same rows (δ = ∞): the batched-least-squares baseline."""
    X, bad = ls_solve_all(prob.rp, prob.ci, prob.hv, prob.z, prob.n, prob.bw, prob.chain_arg())
    return evaluate_solution(prob, X, "ls", 1, "solved" if bad == 0 else "rank_deficient")


# ----------------------------------------------------------------------------- OSQP


class OsqpSolver:
    """(10) as a QP for OSQP, set up once per window shape and then updated.

    Variables per axis (stacked over axes, block-diagonal): [x (n), w (m), a (m), b (m)];
    min ½‖w‖² + δ·1ᵀ(a + b)  s.t.  Hx + w + a − b = z  (l = u = z),  a ≥ 0,  b ≥ 0.
    """

    def __init__(self, eps_abs: float = 1e-8, eps_rel: float = 1e-8, max_iter: int = 50000,
                 polish: bool = True, warm_start: bool = True, cache_size: int = 8, **settings):
        self.settings = dict(eps_abs=eps_abs, eps_rel=eps_rel, max_iter=max_iter, polishing=polish,
                             warm_starting=warm_start, verbose=False, **settings)
        self._cache: OrderedDict = OrderedDict()
        self.cache_size = cache_size
        self.setups = 0

    def _setup(self, prob: HuberProblem):
        import osqp
        import scipy.sparse as sp

        A_, n, m = prob.axes, prob.n, prob.m
        nv = n + 3 * m
        rows, cols, ids = [], [], []
        # H block entries (ids = position in hv.ravel())
        rr = np.repeat(np.arange(m), np.diff(prob.rp))
        nnz = prob.ci.shape[0]
        for a in range(A_):
            rows.append(a * m + rr)
            cols.append(a * nv + prob.ci)
            ids.append(a * nnz + np.arange(nnz))
        base = A_ * nnz
        # identity blocks: w, a, −b  (equality rows), then a ≥ 0, b ≥ 0 rows
        const_vals = []
        k = 0
        for a in range(A_):
            ar = np.arange(m)
            for off, val in ((n, 1.0), (n + m, 1.0), (n + 2 * m, -1.0)):
                rows.append(a * m + ar)
                cols.append(a * nv + off + ar)
                ids.append(base + k + ar)
                const_vals.append(np.full(m, val))
                k += m
        neq = A_ * m
        for a in range(A_):
            ar = np.arange(2 * m)
            rows.append(neq + a * 2 * m + ar)
            cols.append(a * nv + n + m + ar)
            ids.append(base + k + ar)
            const_vals.append(np.ones(2 * m))
            k += 2 * m
        rows = np.concatenate(rows)
        cols = np.concatenate(cols)
        ids = np.concatenate(ids)
        const = np.concatenate(const_vals)
        nrow = neq + A_ * 2 * m
        M = sp.coo_matrix((ids.astype(float) + 1.0, (rows, cols)), shape=(nrow, A_ * nv)).tocsc()
        M.sort_indices()
        perm = M.data.astype(np.int64) - 1  # CSC slot -> entry id
        Pdiag = np.zeros(A_ * nv)
        for a in range(A_):
            Pdiag[a * nv + n: a * nv + n + m] = 1.0
        P = sp.diags(Pdiag).tocsc()
        P = sp.triu(P, format="csc")
        q = np.zeros(A_ * nv)
        l = np.concatenate([prob.z.ravel(), np.zeros(A_ * 2 * m)])
        free = np.where(prob.lsq_mask(), 0.0, np.inf)  # a, b ≤ 0 (so ℓ̄ = 0) on the quadratic rows
        u = np.concatenate([prob.z.ravel(), np.tile(np.concatenate([free, free]), A_)])
        vals = np.concatenate([prob.hv.ravel(), const])
        M.data = vals[perm]
        solver = osqp.OSQP()
        self._fill_q(q, prob)
        solver.setup(P=P, q=q, A=M, l=l, u=u, **self.settings)
        self.setups += 1
        return {"solver": solver, "perm": perm, "const": const, "q": q, "l": l, "u": u, "delta": prob.delta,
                "nv": nv}

    @staticmethod
    def _fill_q(q, prob):
        n, m = prob.n, prob.m
        nv = n + 3 * m
        for a in range(prob.axes):
            q[a * nv + n + m: a * nv + n + 3 * m] = prob.delta

    def solve(self, prob: HuberProblem) -> SolveOut:
        ent, new = _lru_entry(self._cache, self.cache_size, prob.shape_key(), lambda: self._setup(prob))
        if not new:
            vals = np.concatenate([prob.hv.ravel(), ent["const"]])
            neq = prob.axes * prob.m
            ent["l"][:neq] = prob.z.ravel()
            ent["u"][:neq] = prob.z.ravel()
            kw = {"Ax": vals[ent["perm"]], "l": ent["l"], "u": ent["u"]}
            if prob.delta != ent["delta"]:
                self._fill_q(ent["q"], prob)
                ent["delta"] = prob.delta
                kw["q"] = ent["q"]
            ent["solver"].update(**kw)
        res = ent["solver"].solve(raise_error=False)
        nv = ent["nv"]
        X = np.stack([res.x[a * nv: a * nv + prob.n] for a in range(prob.axes)])
        info = res.info
        st = str(getattr(info, "status", ""))
        return evaluate_solution(prob, X, "osqp", int(info.iter), st,
                                 {"osqp_prim_res": float(info.prim_res), "osqp_dual_res": float(info.dual_res)},
                                 {"polished": int(getattr(info, "status_polish", 0)) == 1})


# ----------------------------------------------------------------------------- cvxpy + Clarabel


class CvxpyReference:
    """The literal sum-of-norms problem (10) (c = 1, λ = λ(δ)) in cvxpy, solved by Clarabel.

    min over x, ℓ̄:  1/(2λ²)·‖Hx − z + ℓ̄‖² + √2/(1−λ)·‖ℓ̄‖₁, all axes in one problem. The problem is
    DPP-parametrised in the nonzeros of H, in z and in λ's two weights, and compiled once per shape.
    Its optimal value times λ² is the Huber objective P* (reported as ``objective10`` in ``extra``);
    ``objective`` is P evaluated at its x like every other solver.
    """

    def __init__(self, solver: str = "CLARABEL", tol: float = 1e-10, cache_size: int = 8, **solver_kwargs):
        self.solver = solver
        if solver == "CLARABEL":
            kw = dict(tol_gap_abs=tol, tol_gap_rel=tol, tol_feas=tol, tol_ktratio=1e-8, max_iter=200)
        else:
            kw = {}
        kw.update(solver_kwargs)
        self.kwargs = kw
        self._cache: OrderedDict = OrderedDict()
        self.cache_size = cache_size

    def _setup(self, prob: HuberProblem):
        import cvxpy as cp
        import scipy.sparse as sp

        A_, n, m = prob.axes, prob.n, prob.m
        nnz = prob.ci.shape[0]
        rr = np.repeat(np.arange(m), np.diff(prob.rp))
        # block-diagonal selection matrices over axes: (Hx)_rows = Sr · (hv ∘ (Sc x))
        rows_c = np.arange(A_ * nnz)
        cols_c = np.concatenate([a * n + prob.ci for a in range(A_)])
        Sc = sp.csr_matrix((np.ones(A_ * nnz), (rows_c, cols_c)), shape=(A_ * nnz, A_ * n))
        rows_r = np.concatenate([a * m + rr for a in range(A_)])
        Sr = sp.csr_matrix((np.ones(A_ * nnz), (rows_r, np.arange(A_ * nnz))), shape=(A_ * m, A_ * nnz))
        x = cp.Variable(A_ * n)
        rows_free = np.flatnonzero(np.tile(~prob.lsq_mask(), A_))  # no ℓ̄ on the quadratic rows
        Sf = sp.csr_matrix((np.ones(rows_free.size), (rows_free, np.arange(rows_free.size))),
                           shape=(A_ * m, rows_free.size))
        ell_free = cp.Variable(rows_free.size)
        ell = Sf @ ell_free
        hv = cp.Parameter(A_ * nnz)
        z = cp.Parameter(A_ * m)
        lam = lambda_from_delta(prob.delta)
        wq = 1.0 / (2.0 * lam * lam)  # constants (a parameter times the parametrised Hx is not DPP):
        wl = math.sqrt(2.0) / (1.0 - lam)  # δ is part of the cache key
        Hx = Sr @ cp.multiply(hv, Sc @ x)
        obj = wq * cp.sum_squares(Hx - z + ell) + wl * cp.norm1(ell_free)
        problem = cp.Problem(cp.Minimize(obj))
        return {"problem": problem, "x": x, "ell": ell, "hv": hv, "z": z, "lam": lam}

    def solve(self, prob: HuberProblem) -> SolveOut:
        ent, _ = _lru_entry(self._cache, self.cache_size, prob.shape_key() + (float(prob.delta),),
                            lambda: self._setup(prob))
        lam = ent["lam"]
        ent["hv"].value = prob.hv.ravel()
        ent["z"].value = prob.z.ravel()
        problem = ent["problem"]
        problem.solve(solver=self.solver, **self.kwargs)
        X = np.asarray(ent["x"].value, float).reshape(prob.axes, prob.n)
        stats = problem.solver_stats
        return evaluate_solution(prob, X, "cvxpy-" + self.solver.lower(), int(stats.num_iters or 0),
                                 str(problem.status), None,
                                 {"objective10": float(problem.value),
                                  "objective10_as_huber": float(problem.value) * lam * lam,
                                  "lambda": lam, "solve_time": float(stats.solve_time or float("nan"))})
