"""Shared solver plumbing: IPOPT options, status classification, stats."""

from __future__ import annotations

import contextlib
import contextvars
import re
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field

import casadi as ca
import numpy as np

from ..errors import SolverError

#: IPOPT statuses after which the iterate is returned but flagged as not converged.
SOFT_FAILURES = {
    "Maximum_Iterations_Exceeded",
    "Maximum_CpuTime_Exceeded",
    "Maximum_WallTime_Exceeded",
    "Solved_To_Acceptable_Level",
    "Search_Direction_Becomes_Too_Small",
}


@dataclass
class SolverStats:
    """What a solver reports about one solve.

    ``converged`` is True only for a clean success; anything in
    :data:`SOFT_FAILURES` returns an iterate with ``converged = False``.
    """

    solver: str
    status: str
    converged: bool
    iterations: int
    objective: float
    seconds: float
    extra: dict = field(default_factory=dict)

    def as_attrs(self, prefix: str = "") -> dict:
        """Flat dictionary for HDF5 attributes."""
        d = asdict(self)
        extra = d.pop("extra")
        d.update({f"extra_{k}": v for k, v in extra.items()})
        return {prefix + k: v for k, v in d.items()}


def ipopt_options(tol: float, max_iter: int, extra: dict | None = None) -> dict:
    """Quiet IPOPT options for ``casadi.nlpsol``."""
    opts = {
        "ipopt.print_level": 0,
        "ipopt.sb": "yes",
        "print_time": False,
        "ipopt.tol": tol,
        "ipopt.max_iter": max_iter,
        # no multipliers of the parameters: nothing reads them, and they cost a reverse sweep after every solve
        "calc_lam_p": False,
    }
    if extra:
        opts.update(extra)
    return opts


#: Where a long solve reports how far it got (:func:`solve_progress`); None: nobody listens.
_SOLVE_PROGRESS: contextvars.ContextVar[Callable[[str], None] | None] = contextvars.ContextVar(
    "wss_nlp_solve_progress", default=None
)


@contextlib.contextmanager
def solve_progress(report: Callable[[str], None] | None) -> Iterator[None]:
    """Within the block, long solves call ``report(text)`` as they advance (IPOPT iterations of the solvers built
    with ``report_iterations``, outer sweeps: :func:`report_progress`); ``None`` leaves them silent.

    A context variable: a solve in another thread or process reports nothing unless its caller sets one there.
    """
    token = _SOLVE_PROGRESS.set(report)
    try:
        yield
    finally:
        _SOLVE_PROGRESS.reset(token)


def report_progress(text: str) -> None:
    """Tell whoever listens (:func:`solve_progress`) how far a solve got; nothing when no one does."""
    report = _SOLVE_PROGRESS.get()
    if report is not None:
        report(text)


class IterationReport(ca.Callback):
    """IPOPT's iteration callback: after each iteration, ``report_progress("<what>: IPOPT iteration k, objective
    f")`` (:func:`solve_progress`). It reads only the objective; the iteration counter restarts with every solve
    (:func:`run_nlpsol` calls :meth:`restart`).

    Parameters
    ----------
    what : str
        What the solve is, as the report names it.
    nx, ng, np_ : int
        Sizes of the NLP's variables, constraints and parameters (the callback's input sparsities).
    """

    def __init__(self, what: str, nx: int, ng: int, np_: int):
        ca.Callback.__init__(self)
        self.what, self.iteration = what, 0
        self._sizes = {"x": nx, "lam_x": nx, "g": ng, "lam_g": ng, "p": np_, "lam_p": np_, "f": 1}
        self.construct(re.sub(r"\W+", "_", what).strip("_") + "_iterations", {})  # CasADi: a valid identifier

    def restart(self) -> None:
        self.iteration = 0

    def get_n_in(self) -> int:
        return ca.nlpsol_n_out()

    def get_n_out(self) -> int:
        return 1

    def get_name_in(self, i: int) -> str:
        return ca.nlpsol_out(i)

    def get_name_out(self, i: int) -> str:
        return "ret"

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        n = self._sizes.get(ca.nlpsol_out(i), 0)
        return ca.Sparsity.dense(n, 1) if n else ca.Sparsity(0, 0)

    def eval(self, arg):
        if _SOLVE_PROGRESS.get() is not None:  # IPOPT's numbering: iteration 0 is the starting point
            f = float(arg[ca.nlpsol_out().index("f")])
            report_progress(f"{self.what}: IPOPT iteration {self.iteration}, objective {f:.6g}")
        self.iteration += 1
        return [0]  # 0: go on (non-zero would stop IPOPT)


def iteration_report_options(what: str, x, g, p=None) -> tuple[dict, IterationReport]:
    """nlpsol options that report each IPOPT iteration (:class:`IterationReport`), and the callback, which the
    caller keeps alive as long as the solver (CasADi does not own Python callbacks)."""
    callback = IterationReport(what, x.numel(), g.numel(), 0 if p is None else p.numel())
    return {"iteration_callback": callback}, callback


def gauss_newton_ipopt(
    name: str,
    x,
    f,
    g,
    hess,
    p=None,
    tol: float = 1e-9,
    max_iter: int = 200,
    extra: dict | None = None,
    grad=None,
    report_iterations: str = "",
) -> ca.Function:
    r"""IPOPT on :math:`\min_x f(x; p)` subject to ``g``, with a Gauss-Newton Hessian of the Lagrangian.

    Notes
    -----
    Every NLP of the package is a regularized least-squares problem with
    linear constraints (the radius box), so the Hessian of the Lagrangian is
    :math:`\sigma \nabla^2 f` and :math:`\nabla^2 f \approx 2 (J^\top J + \text{penalty Hessian})`
    =: ``hess`` (an expression in ``x`` and ``p``; only its upper triangle is
    passed). IPOPT then needs no second derivatives of the residual.

    ``grad`` (optional): :math:`\nabla f = 2 J^\top r + \nabla(\text{penalty})`
    written with the same Jacobian as ``hess``. IPOPT asks for the gradient
    and the Hessian at each accepted point, separately; with ``grad`` both
    come from one evaluation of ``(f, grad, hess)`` per point
    (:class:`SharedEvaluation`), so the Jacobian is formed once per
    iteration instead of twice (once by reverse mode for the gradient).
    The objective is then passed behind a callback as well, whose
    derivatives are built only if evaluated: nlpsol's set-up otherwise builds
    the Lagrangian's gradient by reverse mode through the whole graph.
    The returned Function holds the callbacks (attribute ``shared``: the
    objective's and the derivatives').

    ``report_iterations`` (optional): what the solve is; each IPOPT iteration is then reported to
    :func:`solve_progress`'s listener under that name (:class:`IterationReport`, held in ``shared`` too).
    """
    nlp = {"x": x, "f": f, "g": g}
    if p is not None:
        nlp["p"] = p
    options = dict(extra or {})
    shared: tuple = ()
    if report_iterations:
        more, callback = iteration_report_options(report_iterations, x, g, p)
        options.update(more)
        shared = (callback,)
    if grad is not None:
        point, point_names = ([x], ["x"]) if p is None else ([x, p], ["x", "p"])
        # the objective behind a callback too: IPOPT needs no derivatives of it here, and nlpsol's set-up
        # would build a reverse sweep through its graph (0.1-0.4 s for the coupled misfit at h = 0.3 mm)
        derivatives = SharedEvaluation(
            ca.Function(f"{name}_derivatives", point, [f, grad, hess], point_names, ["f", "grad", "hess"])
        )
        objective = EagerObjective(ca.Function(f"{name}_objective", point, [f], point_names, ["f"]), derivatives)
        nlp["f"] = objective(*point)
        shared += (objective, derivatives)
        # the same inputs, fresh symbols: these functions read the shared outputs, not the expressions
        x = ca.MX.sym("x", x.sparsity())
        p = None if p is None else ca.MX.sym("p", p.sparsity())
        values = derivatives.call({"x": x} if p is None else {"x": x, "p": p})
        hess = values["hess"]
        io = {"x": x, "f": values["f"], "grad_f_x": values["grad"]}
        if p is not None:
            io["p"] = p
        options["grad_f"] = ca.Function("nlp_grad_f", io, ["x", "p"], ["f", "grad_f_x"])
    sigma = ca.MX.sym("sigma")
    io = {"x": x, "lam_f": sigma, "hess_gamma_x_x": sigma * ca.triu(hess)}
    if p is not None:
        io["p"] = p
    options["hess_lag"] = ca.Function("nlp_hess_l", io, ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
    solver = ca.nlpsol(name, "ipopt", nlp, ipopt_options(tol, max_iter, options))
    if shared:
        solver.shared = shared  # type: ignore[attr-defined]  # CasADi's rule: keep callbacks while in use
    return solver


class _DeferredDerivatives:
    """Forward and reverse derivatives of a callback that are those of ``self.built()`` (a CasADi Function),
    each built only when first evaluated (:func:`_deferred_derivative`); the callback keeps them in ``_kept``."""

    _kept: list

    def built(self) -> ca.Function:  # pragma: no cover - abstract
        raise NotImplementedError

    def has_forward(self, nfwd):
        return True

    def get_forward(self, nfwd, name, inames, onames, opts):
        return _deferred_derivative(self, self.built, False, nfwd, name, inames, onames, opts)

    def has_reverse(self, nadj):
        return True

    def get_reverse(self, nadj, name, inames, onames, opts):
        return _deferred_derivative(self, self.built, True, nadj, name, inames, onames, opts)


class SharedEvaluation(_DeferredDerivatives, ca.Callback):
    """A CasADi Function evaluated once per distinct input and reused for repeated calls at the same point.

    IPOPT evaluates the gradient and the Hessian of the Lagrangian at the same
    iterate through separate functions; this callback lets both read the
    outputs of one evaluation (the last point only: the inputs are compared
    exactly, byte for byte). The wrapped function runs in one persistent
    ``Function.buffer`` on NumPy memory: a call from Python allocates and
    zeroes CasADi's work vector (all the intermediates, megabytes for the
    coupled misfit) every time, which cost a third of an evaluation at
    h = 0.3 mm. Its derivatives are the wrapped function's own
    (:meth:`casadi.Function.forward`, :meth:`casadi.Function.reverse`, and
    theirs in turn), built only when one is evaluated: nlpsol's set-up asks
    for a gradient function it does not call when the gradient and Hessian
    are supplied, and building it through a large graph costs 0.1-0.4 s
    (the coupled misfit at h = 0.3 mm).
    """

    def __init__(self, function: ca.Function):
        ca.Callback.__init__(self)
        self.function = function
        self._key: bytes | None = None
        self._inputs = [np.zeros(function.nnz_in(i)) for i in range(function.n_in())]
        self._outputs = [np.zeros(function.nnz_out(i)) for i in range(function.n_out())]
        self._run: tuple | None = None  # (FunctionBuffer, its eval), made on the first evaluation
        self.requested: bytes | None = None  # the last point a caller of this callback asked for
        self._kept: list = []  # derivative callbacks (CasADi's rule: keep them while in use)
        self.evaluations = 0
        self.construct(f"shared_{function.name()}", {})

    def built(self) -> ca.Function:
        return self.function

    def get_n_in(self):
        return self.function.n_in()

    def get_n_out(self):
        return self.function.n_out()

    def get_name_in(self, i):
        return self.function.name_in(i)

    def get_name_out(self, i):
        return self.function.name_out(i)

    def get_sparsity_in(self, i):
        return self.function.sparsity_in(i)

    def get_sparsity_out(self, i):
        return self.function.sparsity_out(i)

    def has_eval_buffer(self):
        return True

    @staticmethod
    def _key_of(arg) -> bytes:
        # CasADi passes None for an input that is structurally zero
        return b"|".join(b"" if a is None else bytes(a) for a in arg)

    def evaluate(self, arg) -> list[np.ndarray]:
        """The outputs' nonzeros at the input buffers ``arg`` (evaluated only if the point changed)."""
        key = self._key_of(arg)
        if key != self._key:
            for target, a in zip(self._inputs, arg):
                target[:] = 0.0 if a is None else np.frombuffer(a, dtype=np.float64)
            if self._run is None:
                self._run = bound_buffer(self.function, self._inputs, self._outputs)
            self._run[1]()
            self._key = key
            self.evaluations += 1
        return self._outputs

    def eval_buffer(self, arg, res):
        self.requested = self._key_of(arg)
        for r, value in zip(res, self.evaluate(arg)):
            if r is not None:  # None: an output nobody reads
                np.frombuffer(r, dtype=np.float64)[:] = value
        return 0


class EagerObjective(SharedEvaluation):
    """The objective ``f`` of :func:`gauss_newton_ipopt`, read from the shared ``(f, grad, hess)`` evaluation.

    IPOPT evaluates ``f`` at a trial point and, when it accepts the step (a
    Gauss-Newton step near the start almost always is), the gradient and
    Hessian at the same point. Evaluating them together with ``f`` saves the
    separate pass through the residual (a fifth of a coupled iteration, a
    third with a near-wall layer). After a rejected trial (the previous
    ``f`` point got no gradient request) the next ``f`` comes from
    ``function`` alone, the same expression in a graph without the Jacobian
    (equal values), until a step is accepted again. Its derivatives are
    ``function``'s (deferred, as for :class:`SharedEvaluation`).
    """

    def __init__(self, function: ca.Function, derivatives: SharedEvaluation):
        self.derivatives = derivatives
        self.eager_evaluations = 0
        super().__init__(function)

    def evaluate(self, arg) -> list[np.ndarray]:
        key = self._key_of(arg)
        # IPOPT asks for the derivatives at a trial point only once it has accepted the step
        accepted = self._key is None or self._key == self.derivatives.requested
        if key != self._key and accepted:
            self._outputs[0][:] = self.derivatives.evaluate(arg)[0]
            self._key = key
            self.eager_evaluations += 1
            return self._outputs
        return super().evaluate(arg)


def _deferred_derivative(owner, function, reverse: bool, n: int, name, inames, onames, opts) -> ca.Function:
    """CasADi's ``n``-direction forward or reverse derivative of ``function()``, built when first evaluated.

    ``owner`` (a callback with ``get_sparsity_in/out`` and a ``_kept`` list) keeps the deferred callback.
    """
    sp_in = [owner.get_sparsity_in(i) for i in range(owner.get_n_in())]
    sp_out = [owner.get_sparsity_out(i) for i in range(owner.get_n_out())]
    seeds, sens = (sp_out, sp_in) if reverse else (sp_in, sp_out)
    lazy = _Deferred(
        f"{name}_deferred",
        sp_in + sp_out + [ca.repmat(sp, 1, n) for sp in seeds],
        [ca.repmat(sp, 1, n) for sp in sens],
        lambda: function().reverse(n) if reverse else function().forward(n),
    )
    owner._kept.append(lazy)
    args = [ca.MX.sym(f"a{i}", sp) for i, sp in enumerate(lazy.sparsities[0])]
    return ca.Function(name, args, lazy.call(args), inames, onames, opts)


class _Deferred(_DeferredDerivatives, ca.Callback):
    """A function built by ``build()`` on its first evaluation (sparsities given up front); its derivatives
    are deferred the same way."""

    def __init__(self, name: str, sp_in: list, sp_out: list, build):
        ca.Callback.__init__(self)
        self.sparsities, self.build = (sp_in, sp_out), build
        self.function: ca.Function | None = None
        self._kept: list = []
        self.construct(name, {})

    def built(self) -> ca.Function:
        if self.function is None:
            self.function = self.build()
        assert self.function is not None
        return self.function

    def get_n_in(self):
        return len(self.sparsities[0])

    def get_n_out(self):
        return len(self.sparsities[1])

    def get_sparsity_in(self, i):
        return self.sparsities[0][i]

    def get_sparsity_out(self, i):
        return self.sparsities[1][i]

    def eval(self, arg):
        out = self.built()(*arg)
        return list(out) if isinstance(out, (list, tuple)) else [out]


def bound_buffer(function: ca.Function, inputs: list, outputs: list) -> tuple:
    """``function.buffer()`` reading ``inputs`` and writing ``outputs`` (NumPy arrays of the nonzeros, kept by
    the caller): ``(buffer, run)``; keep the buffer while ``run`` is used."""
    buf, run = function.buffer()
    for i, held in enumerate(inputs):
        buf.set_arg(i, memoryview(held))  # type: ignore[call-arg]  # the size comes with the buffer
    for i, r in enumerate(outputs):
        buf.set_res(i, memoryview(r))  # type: ignore[call-arg]
    return buf, run


class DenseCall:
    """``function``'s outputs as NumPy arrays of the outputs' shapes, evaluated in one persistent buffer.

    CasADi writes the dense outputs straight into NumPy memory (``Function.buffer``): converting a large
    ``DM`` costs about 55 ns per entry (64 ms for a 10 000 x 119 Jacobian block, more than computing it), and
    one buffer serves every call (a new one allocates and zeroes CasADi's work vector each time). Every input
    and output must be dense (:func:`casadi.densify` them in the graph).
    """

    def __init__(self, function: ca.Function):
        for i in range(function.n_in()):
            if not function.sparsity_in(i).is_dense():
                raise ValueError(f"DenseCall: input {i} of {function.name()} is not dense")
        for i in range(function.n_out()):
            if not function.sparsity_out(i).is_dense():
                raise ValueError(f"DenseCall: output {i} of {function.name()} is not dense (densify it)")
        self.function = function
        self._inputs = [np.empty(function.nnz_in(i)) for i in range(function.n_in())]
        self._outputs = [np.empty(function.nnz_out(i)) for i in range(function.n_out())]
        self._buffer, self._run = bound_buffer(function, self._inputs, self._outputs)

    def __call__(self, *args) -> list[np.ndarray]:
        """The outputs at ``args`` (arrays in the inputs' shapes, or numbers for every entry); fresh arrays."""
        for held, a in zip(self._inputs, args):
            a = np.asarray(a, dtype=float)
            held[:] = np.ravel(a, order="F") if a.size > 1 else float(a)  # CasADi's memory is column-major
        self._run()
        return [r.reshape(self.function.size_out(i)[::-1]).T.copy() for i, r in enumerate(self._outputs)]


def run_nlpsol(solver: ca.Function, what: str, **args) -> tuple[dict, SolverStats]:
    """Call an ``nlpsol`` and classify its return status.

    Raises
    ------
    SolverError
        For hard failures (invalid numbers, restoration failure, infeasible
        problem, ...): nothing usable was computed.
    """
    for held in getattr(solver, "shared", ()):
        if isinstance(held, IterationReport):
            held.restart()
    t0 = time.perf_counter()
    try:
        sol = solver(**args)
    except RuntimeError as exc:  # evaluation errors surface as RuntimeError
        last = [ln for ln in str(exc).splitlines() if ln.strip()][-1:] or ["unknown error"]
        raise SolverError(f"{what}: IPOPT raised an error: {last[0].strip()}") from exc
    seconds = time.perf_counter() - t0
    st = solver.stats()
    status = str(st.get("return_status", "unknown"))
    success = bool(st.get("success", False))
    if not success and status not in SOFT_FAILURES:
        raise SolverError(f"{what}: IPOPT failed with status {status}")
    stats = SolverStats(
        solver="ipopt",
        status=status,
        converged=success and status == "Solve_Succeeded",
        iterations=int(st.get("iter_count", -1)),
        objective=float(sol["f"]),
        seconds=seconds,
    )
    return sol, stats
