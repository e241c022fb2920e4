"""Dense linear maps evaluated by BLAS inside CasADi graphs, with exact derivatives of every order.

CasADi's own products with constant dense matrices are plain loops (about
5-10x slower than BLAS at the sizes of the magnitude models) and converting
a large NumPy array to a ``casadi.DM`` constant costs about as much as
building the rest of a solver. The maps here keep their matrix in NumPy:

* :class:`MatrixProduct` -- ``X -> A X`` (the radius basis at the
  quadrature points, eq. (discForw): ``R(phi_j) = b(phi_j)^T c``);
* :class:`GroupedWeightedSum` -- ``s -> M diag(s) B`` with ``M`` the mean
  over consecutive groups of rows: the chain rule of a voxel average,
  ``dF_i/dc = |G_i|^{-1} sum_{j in G_i} s_j b_j^T``, used for the
  Gauss-Newton Jacobian of the geometry functional.

Both are linear, so the forward derivative is the map applied to the seeds
and the reverse derivative its adjoint (``tests/test_operators.py`` checks
each pair with a dot test and against CasADi's own products). Keep a
reference to an instance while functions built from it live (CasADi's rule
for callbacks); derived maps are kept by their parent.
"""

from __future__ import annotations

import numpy as np

import casadi as ca


class DenseCallback(ca.Callback):
    """One dense input of shape ``shape_in`` to one dense output of shape ``shape_out``, evaluated in place."""

    def __init__(self, name: str, shape_in: tuple, shape_out: tuple):
        ca.Callback.__init__(self)
        self.shape_in, self.shape_out = shape_in, shape_out
        self.construct(name, {})

    def get_n_in(self):
        return 1

    def get_n_out(self):
        return 1

    def get_sparsity_in(self, i):
        return ca.Sparsity.dense(*self.shape_in)

    def get_sparsity_out(self, i):
        return ca.Sparsity.dense(*self.shape_out)

    def has_eval_buffer(self):
        return True


class _LinearCallback(DenseCallback):
    """A linear map ``X -> L(X)`` on ``cols`` side-by-side columns; subclasses give ``apply`` and shapes."""

    def __init__(self, name: str, n_in: int, n_out: int, cols: int):
        self.n_in_, self.n_out_, self.cols = int(n_in), int(n_out), int(cols)
        self._derived: dict = {}
        super().__init__(name, (self.n_in_, self.cols), (self.n_out_, self.cols))

    def apply(self, x: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def derived(self, cols: int, flip: bool) -> _LinearCallback:  # pragma: no cover - abstract
        """The same map (or, with ``flip``, its adjoint) on ``cols`` columns, built once."""
        raise NotImplementedError

    def eval_buffer(self, arg, res):
        # CasADi's memory is column-major: read and write it in place, no copies of the inputs
        x = np.frombuffer(arg[0], dtype=np.float64).reshape(self.cols, self.n_in_).T
        out = np.frombuffer(res[0], dtype=np.float64).reshape(self.cols, self.n_out_).T
        out[...] = self.apply(x)
        return 0

    def _kept(self, key, make):
        if key not in self._derived:
            self._derived[key] = make()
        return self._derived[key]

    def has_forward(self, nfwd):
        return True

    def get_forward(self, nfwd, name, inames, onames, opts):
        x, y = ca.MX.sym("x", self.sparsity_in(0)), ca.MX.sym("y", self.sparsity_out(0))
        # nfwd seeds side by side: the same map on nfwd times as many columns
        seed = ca.MX.sym("seed", ca.repmat(self.sparsity_in(0), 1, nfwd))
        out = self.derived(self.cols * nfwd, False)(seed)
        return ca.Function(name, [x, y, seed], [out], inames, onames, opts)

    def has_reverse(self, nadj):
        return True

    def get_reverse(self, nadj, name, inames, onames, opts):
        x, y = ca.MX.sym("x", self.sparsity_in(0)), ca.MX.sym("y", self.sparsity_out(0))
        seed = ca.MX.sym("seed", ca.repmat(self.sparsity_out(0), 1, nadj))
        out = self.derived(self.cols * nadj, True)(seed)
        return ca.Function(name, [x, y, seed], [out], inames, onames, opts)


class MatrixProduct(_LinearCallback):
    """``X -> A X`` (or ``A^T X`` with ``adjoint``) for a dense NumPy matrix ``A`` of shape ``(m, n)``.

    Notes
    -----
    One BLAS product per evaluation, ``2 m n cols`` flops.
    """

    def __init__(self, a: np.ndarray, cols: int = 1, adjoint: bool = False, _parent: MatrixProduct | None = None):
        self.a: np.ndarray = np.ascontiguousarray(a, dtype=float) if _parent is None else _parent.a
        self.at: np.ndarray = np.ascontiguousarray(self.a.T) if _parent is None else _parent.at
        self.adjoint = adjoint
        self._root: MatrixProduct = self if _parent is None else _parent._root
        m, n = self.a.shape
        super().__init__(f"matprod_{'adj' if adjoint else 'fwd'}_{cols}", *((m, n) if adjoint else (n, m)), cols)

    def apply(self, x: np.ndarray) -> np.ndarray:
        return (self.at if self.adjoint else self.a) @ x

    def derived(self, cols: int, flip: bool) -> MatrixProduct:
        root, adjoint = self._root, self.adjoint != flip
        return root._kept((cols, adjoint), lambda: MatrixProduct(root.a, cols, adjoint, root))


class GroupedWeightedSum(_LinearCallback):
    r"""``s -> M diag(s) B``: ``B`` (shape ``(m, n)``) weighted row-wise by ``s``, averaged over groups of rows.

    Notes
    -----
    Rows ``g k .. g k + g - 1`` form group ``k`` (``m = g K``), so
    ``(M diag(s) B)_{k,:} = g^{-1} \sum_{j<g} s_{gk+j} B_{gk+j,:}`` with
    ``K n`` outputs (column-major, as CasADi stores a ``(K, n)`` matrix).
    The adjoint takes ``Y`` of shape ``(K, n)`` to
    ``s_i = g^{-1} \sum_l B_{il} Y_{k(i),l}``. About ``2 m n`` flops either way.
    Several columns of ``s`` give the maps side by side.
    """

    def __init__(self, b: np.ndarray, group: int, cols: int = 1, adjoint: bool = False, _parent=None):
        self.b = np.ascontiguousarray(b, dtype=float) if _parent is None else _parent.b
        self.group, self.adjoint = int(group), adjoint
        self._root = self if _parent is None else _parent._root
        m, n = self.b.shape
        if m % self.group:
            raise ValueError(f"GroupedWeightedSum: {m} rows do not split into groups of {self.group}")
        self.k = m // self.group
        dims = (self.k * n, m) if adjoint else (m, self.k * n)
        super().__init__(f"gws_{'adj' if adjoint else 'fwd'}_{cols}", *dims, cols)

    def apply(self, x: np.ndarray) -> np.ndarray:
        m, n = self.b.shape
        g, k, cols = self.group, self.k, x.shape[1]
        if not self.adjoint:  # x: (m, cols) weights -> (k n, cols), each column a (k, n) block in column order
            out = np.einsum("kgc,kgn->nkc", x.reshape(k, g, cols), self.b.reshape(k, g, n)) / g
            return out.reshape(n * k, cols)
        y = x.reshape(n, k, cols)  # column-major (k, n) blocks
        return (np.einsum("kgn,nkc->kgc", self.b.reshape(k, g, n), y) / g).reshape(m, cols)

    def derived(self, cols: int, flip: bool) -> GroupedWeightedSum:
        root, adjoint = self._root, self.adjoint != flip
        return root._kept((cols, adjoint), lambda: GroupedWeightedSum(root.b, root.group, cols, adjoint, root))


class Gram(DenseCallback):
    r"""``J -> J^T J`` for a dense ``(m, n)`` matrix ``J``, one BLAS product (the Gauss-Newton Hessian).

    Notes
    -----
    About ``m n^2`` flops (CasADi's own product is a loop, about 10x
    slower for ``m`` in the thousands). Derivatives: forward
    ``dJ^T J + J^T dJ``, reverse ``J (Y + Y^T)``, written with CasADi's
    products (they are rarely needed: the solvers only evaluate the
    Hessian).
    """

    def __init__(self, m: int, n: int):
        self.m, self.n = int(m), int(n)
        super().__init__(f"gram_{m}x{n}", (self.m, self.n), (self.n, self.n))

    def eval_buffer(self, arg, res):
        j = np.frombuffer(arg[0], dtype=np.float64).reshape(self.n, self.m)  # J^T, row-major view of column-major J
        out = np.frombuffer(res[0], dtype=np.float64).reshape(self.n, self.n)
        out[...] = j @ j.T
        return 0

    def has_forward(self, nfwd):
        return True

    def get_forward(self, nfwd, name, inames, onames, opts):
        j, y = ca.MX.sym("j", self.m, self.n), ca.MX.sym("y", self.n, self.n)
        seed = ca.MX.sym("seed", self.m, self.n * nfwd)
        out = [ca.mtimes(d.T, j) + ca.mtimes(j.T, d) for d in ca.horzsplit(seed, self.n)]
        return ca.Function(name, [j, y, seed], [ca.horzcat(*out)], inames, onames, opts)

    def has_reverse(self, nadj):
        return True

    def get_reverse(self, nadj, name, inames, onames, opts):
        j, y = ca.MX.sym("j", self.m, self.n), ca.MX.sym("y", self.n, self.n)
        seed = ca.MX.sym("seed", self.n, self.n * nadj)
        out = [ca.mtimes(j, s + s.T) for s in ca.horzsplit(seed, self.n)]
        return ca.Function(name, [j, y, seed], [ca.horzcat(*out)], inames, onames, opts)


class BlockGram(ca.Callback):
    r"""``(A, B, C, r_1, r_2) -> (J^T J, J^T r)`` for ``J = [[A, 0], [sqrt(w) B, sqrt(w) C F]]`` and
    ``r = [r_1; sqrt(w) r_2]``, without forming ``J``.

    Notes
    -----
    ``A`` is ``(m1, n1)``, ``B`` ``(m2, n1)``, ``C`` ``(m2, k)``, ``F`` a
    constant ``(k, n2)`` (``right``; default the identity, ``k = n2``),
    ``r_1`` ``(m1, 1)``, ``r_2`` ``(m2, 1)``, ``w > 0`` a constant. ``C``
    may come as column blocks ``C_1, ..., C_p`` of the ``widths`` given
    (inputs ``A, B, C_1, ..., C_p, r_1, r_2``): concatenating them in a
    CasADi graph costs more than the products. The results are

    .. math::

        J^\top J = \begin{pmatrix} A^\top A + w B^\top B & w B^\top C F \\
                    w F^\top C^\top B & w F^\top (C^\top C) F \end{pmatrix}, \qquad
        J^\top r = \begin{pmatrix} A^\top r_1 + w B^\top r_2 \\ w F^\top C^\top r_2 \end{pmatrix},

    BLAS products, about ``m1 n1^2 + m2 (n1 + k)^2 / 2`` flops (``C^T C``
    by a symmetric rank-k update, half of ``C F``'s ``2 m2 k n2``). The
    coupled Jacobian has this shape (magnitude rows depend on ``c_R`` only);
    concatenating and scaling its blocks in the graph cost as much as the
    blocks themselves (measured at h = 0.3 mm: 40 ms of 85 per evaluation),
    and CasADi's ``J^T r`` transposes the blocks first (about 10 ms).
    Evaluation only (the Gauss-Newton Hessian is never differentiated).
    """

    def __init__(
        self,
        m1: int,
        n1: int,
        m2: int,
        n2: int,
        weight: float,
        right: np.ndarray | None = None,
        widths: tuple[int, ...] | None = None,
    ):
        ca.Callback.__init__(self)
        self.right = None if right is None else np.ascontiguousarray(right, dtype=float)
        self.k = n2 if right is None else self.right.shape[0]  # type: ignore[union-attr]
        if right is not None and self.right.shape[1] != n2:  # type: ignore[union-attr]
            raise ValueError(f"BlockGram: right factor of shape {np.shape(right)} does not give {n2} columns")
        self.widths = (self.k,) if widths is None else tuple(int(w) for w in widths)
        if sum(self.widths) != self.k:
            raise ValueError(f"BlockGram: column blocks {self.widths} do not add up to {self.k} columns")
        self.m1, self.n1, self.m2, self.n2, self.weight = int(m1), int(n1), int(m2), int(n2), float(weight)
        self.construct(f"block_gram_{m1}_{m2}x{n1}_{n2}", {})

    def get_n_in(self):
        return 4 + len(self.widths)

    def get_n_out(self):
        return 2

    def get_sparsity_in(self, i):
        shapes = [(self.m1, self.n1), (self.m2, self.n1), *[(self.m2, w) for w in self.widths]]
        shapes += [(self.m1, 1), (self.m2, 1)]
        return ca.Sparsity.dense(*shapes[i])

    def get_sparsity_out(self, i):
        n = self.n1 + self.n2
        return ca.Sparsity.dense(n, n) if i == 0 else ca.Sparsity.dense(n, 1)

    def has_eval_buffer(self):
        return True

    def eval_buffer(self, arg, res):
        n1, n, f, p = self.n1, self.n1 + self.n2, self.right, len(self.widths)
        # row-major views of the column-major inputs are their transposes
        at = np.frombuffer(arg[0], dtype=np.float64).reshape(n1, self.m1)
        bt = np.frombuffer(arg[1], dtype=np.float64).reshape(n1, self.m2)
        cts = [np.frombuffer(a, dtype=np.float64).reshape(wd, self.m2) for a, wd in zip(arg[2 : 2 + p], self.widths)]
        r1, r2 = np.frombuffer(arg[2 + p], dtype=np.float64), np.frombuffer(arg[3 + p], dtype=np.float64)
        edges = np.cumsum((0,) + self.widths)
        w = self.weight
        if res[0] is not None:  # CasADi passes None for an output nobody reads
            out = np.frombuffer(res[0], dtype=np.float64).reshape(n, n)  # symmetric: layout does not matter
            out[:n1, :n1] = at @ at.T + w * (bt @ bt.T)
            ctc, btc = np.empty((self.k, self.k)), np.empty((n1, self.k))
            for i, ci in enumerate(cts):
                rows = slice(edges[i], edges[i + 1])
                btc[:, rows] = bt @ ci.T
                for j, cj in enumerate(cts[: i + 1]):  # ci @ ci.T: NumPy calls the symmetric update (syrk)
                    ctc[rows, edges[j] : edges[j + 1]] = ci @ cj.T
                    ctc[edges[j] : edges[j + 1], rows] = ctc[rows, edges[j] : edges[j + 1]].T
            if f is not None:
                ctc, btc = f.T @ ctc @ f, btc @ f
            out[:n1, n1:] = w * btc
            out[n1:, :n1] = out[:n1, n1:].T
            out[n1:, n1:] = w * ctc
        if res[1] is not None:
            jtr = np.frombuffer(res[1], dtype=np.float64)
            jtr[:n1] = at @ r1 + w * (bt @ r2)
            ctr = np.concatenate([ci @ r2 for ci in cts])
            jtr[n1:] = w * (ctr if f is None else f.T @ ctr)
        return 0


class ScatteredBlocks(_LinearCallback):
    r"""``s -> [P diag(s) b_1, ..., P diag(s) b_n]``: row-weighted columns of ``B`` scattered into images.

    Notes
    -----
    ``P`` puts the ``m`` rows at the flat (column-major) positions ``index``
    of an image of ``shape = (fy, fx)`` (zero elsewhere); the ``n`` images
    lie side by side, one ``(fy, n fx)`` matrix (CasADi's column-major
    layout), ready for a batched separable map
    (:class:`wss_nlp.models.kspace.SeparablePSF`). The adjoint takes such images
    ``Y_j`` to ``sum_j b_j * Y_j[index]``. About ``m n`` operations either way.
    Used for the k-space Gauss-Newton Jacobian, ``dF/dc_j = K (H' b_j) K^T``.
    """

    def __init__(
        self, b: np.ndarray, index: np.ndarray, shape: tuple, cols: int = 1, adjoint: bool = False, _parent=None
    ):
        self.b = np.ascontiguousarray(b, dtype=float) if _parent is None else _parent.b
        self.index = np.asarray(index, dtype=np.int64) if _parent is None else _parent.index
        self.shape, self.adjoint = (int(shape[0]), int(shape[1])), adjoint
        self._root = self if _parent is None else _parent._root
        self.bt = np.ascontiguousarray(self.b.T) if _parent is None else _parent.bt  # rows written contiguously
        m, n = self.b.shape
        size = self.shape[0] * self.shape[1] * n
        super().__init__(f"scatter_{'adj' if adjoint else 'fwd'}_{cols}", *((size, m) if adjoint else (m, size)), cols)

    def get_sparsity_in(self, i):
        if self.adjoint:
            return ca.Sparsity.dense(self.shape[0], self.shape[1] * self.b.shape[1] * self.cols)
        return super().get_sparsity_in(i)

    def get_sparsity_out(self, i):
        if not self.adjoint:
            return ca.Sparsity.dense(self.shape[0], self.shape[1] * self.b.shape[1] * self.cols)
        return super().get_sparsity_out(i)

    def eval_buffer(self, arg, res):
        # column-major images: flat blocks of fy * fx values, image j of column k at (k n + j) fy fx
        m, n = self.b.shape
        pixels = self.shape[0] * self.shape[1]
        x = np.frombuffer(arg[0], dtype=np.float64)
        out = np.frombuffer(res[0], dtype=np.float64)
        if not self.adjoint:
            out[:] = 0.0
            images = out.reshape(self.cols * n, pixels)
            for k, s in enumerate(x.reshape(self.cols, m)):
                images[k * n : (k + 1) * n, self.index] = self.bt * s[None, :]
        else:
            images = x.reshape(self.cols * n, pixels)
            for k in range(self.cols):
                out[k * m : (k + 1) * m] = np.einsum("jm,mj->m", images[k * n : (k + 1) * n][:, self.index], self.b)
        return 0

    def derived(self, cols: int, flip: bool) -> ScatteredBlocks:
        root, adjoint = self._root, self.adjoint != flip
        return root._kept((cols, adjoint), lambda: ScatteredBlocks(root.b, root.index, root.shape, cols, adjoint, root))
