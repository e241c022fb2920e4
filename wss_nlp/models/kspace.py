"""The scanner's point-spread function: a Cartesian k-space measurement model.

A Cartesian acquisition samples the Fourier transform of the complex signal
``s = rho chi_Omega exp(i pi u / venc)`` at the ``N`` lowest frequencies per
axis, multiplies them by a k-space filter ``w`` and reconstructs ``n = F N``
image points over the same field of view (``F`` the zero-filling factor).
Every image value is then the signal convolved with a periodic,
separable point-spread function (PSF) instead of the voxel average of
Sec. 7 (the "box" model):

.. math::

    I(x_j, y_i) = \\int s(x, y)\\, K_y(y_i - y)\\, K_x(x_j - x)\\, dx\\, dy,
    \\qquad
    K(d) = \\frac{1}{L} \\sum_{|k| \\le N/2} w'(k) \\cos\\frac{2 \\pi k d}{L},

with ``L`` the field of view and ``w'`` the filter with half weight on the
two Nyquist lines ``k = +-N/2`` of an even ``N``: the real part of the
scanner's asymmetric sampling ``-N/2 <= k < N/2`` (the imaginary part it adds
is one k-space line, below 1 % of the edge signal; measured in
``tests/test_kspace.py``). The integral is the model's ``q x q`` sub-voxel
midpoint rule, so :meth:`PSF.kernel` is an ``(n, n q)`` matrix per axis and
the model costs two dense products per image instead of one block sum
(``O(n^2 q)`` per row of the window instead of ``O(q^2)`` per voxel).

Filters (``w`` as a function of ``x = k / (N/2)`` in [-1, 1]): "none";
"hamming" ``0.54 + 0.46 cos(pi x)``; "tukey" (tapered cosine, flat for
``|x| <= 0.5``, a half cosine down to 0 at ``|x| = 1``); "fermi"
``1 / (1 + exp((|x| - 0.9) / 0.05))``, normalized to ``w(0) = 1``. They are
applied per axis (separable). Vendors' exact parameters differ and are not
in the DICOM headers we read; these are common textbook settings.

:func:`acquire` simulates such an acquisition independently of the model:
the signal on a fine grid, its FFT, the central crop, the filter, zero-filling
and the inverse FFT (``numpy.fft``), noise added in k-space.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

import casadi as ca

from ..core import operators
from ..core import radius as rad
from ..errors import InputError
from ..core.schema import option

ACQUISITIONS = ("auto", "box", "kspace")
FILTERS = ("none", "hamming", "tukey", "fermi")
#: ``--kspace-filter auto``: the filter whose geometry fit explains the magnitude best (wss_nlp.choice).
FILTER_CHOICES = ("auto",) + FILTERS
TUKEY_FLAT = 0.5  # flat part of the Tukey window, fraction of k_max
FERMI_RADIUS, FERMI_WIDTH = 0.9, 0.05  # fractions of k_max
#: Acquired voxels beyond the wall annulus whose magnitude the geometry fit includes (ringing decays like 1/d).
WINDOW_ACQUIRED_VOXELS = 3.0
#: Smoothing of |.| in the magnitude model (fraction of the lumen signal), far below any image's noise.
ABS_SMOOTHING = 1e-3


@dataclass(frozen=True)
class AcquisitionOptions:
    """How the scanner turned the signal into voxels.

    Attributes
    ----------
    model : {"auto", "box", "kspace"}
        "box": every voxel is the mean of the signal over the voxel (the
        paper's model, Sec. 7). "kspace": the PSF of a Cartesian acquisition
        with ``kspace_filter`` and ``zero_fill`` (:class:`PSF`). "auto"
        (default): "kspace" when the file states its acquired resolution
        (``acquired_voxel_size_mm``, written by ``wss-nlp import`` from the
        DICOM headers), else "box".
    kspace_filter : {"auto", "none", "hamming", "tukey", "fermi"}
        "auto" (default): the filter whose geometry fit leaves the smallest
        magnitude misfit (:func:`wss_nlp.parameters.kspace_filter.kspace_filter`); the
        standard DICOM headers do not state it.
    zero_fill : float or None
        Reported voxels per acquired voxel along each axis (2 for an image
        interpolated to twice the acquired matrix); None: the file's
        ``acquired_voxel_size_mm`` divided by its voxel size, else 1.
    """

    schema_group = "acquisition model (k-space point-spread function)"

    model: str = option(
        "auto",
        "measurement model of a voxel: box (voxel mean, the paper's), kspace (Cartesian point-spread function), "
        "or auto (kspace when the file states acquired_voxel_size_mm, else box)",
        cli="--acquisition",
        toml=("acquisition",),
        choices=ACQUISITIONS,
    )
    kspace_filter: str = option(
        "auto",
        "k-space filter the scanner applied (with the kspace model); auto: the one whose geometry fit "
        "explains the magnitude best",
        cli="--kspace-filter",
        toml=("kspace_filter",),
        choices=FILTER_CHOICES,
    )
    zero_fill: float | None = option(
        None,
        "reported voxels per acquired voxel (default: from the file's acquired_voxel_size_mm, else 1)",
        cli="--zero-fill",
        toml=("zero_fill",),
    )

    def __post_init__(self):
        if self.model not in ACQUISITIONS:
            raise InputError(f"acquisition model must be one of {', '.join(ACQUISITIONS)}, got {self.model!r}")
        if self.kspace_filter not in FILTER_CHOICES:
            raise InputError(f"k-space filter must be one of {', '.join(FILTER_CHOICES)}, got {self.kspace_filter!r}")
        if self.zero_fill is not None and not self.zero_fill >= 1:
            raise InputError(f"--zero-fill must be >= 1 (reported voxels per acquired voxel), got {self.zero_fill}")

    def psf(self, voxel_size_mm, acquired_voxel_size_mm=None, where: str = "") -> PSF | None:
        """The PSF of a slice with ``voxel_size_mm = (dy, dx)``, or None for the box model.

        Its filter is "auto" when it is to be chosen from the data
        (:func:`wss_nlp.parameters.kspace_filter.kspace_filter`).
        """
        if self.model == "box" or (self.model == "auto" and acquired_voxel_size_mm is None):
            return None
        fill: tuple[float, float]
        if self.zero_fill is not None:
            fill = (float(self.zero_fill), float(self.zero_fill))
        elif acquired_voxel_size_mm is not None:
            acq = np.asarray(acquired_voxel_size_mm, dtype=float)
            fill = (float(acq[0] / voxel_size_mm[0]), float(acq[1] / voxel_size_mm[1]))
            if min(fill) < 1 - 1e-6:
                raise InputError(
                    f"{where}acquired_voxel_size_mm {tuple(acq)} is smaller than the voxel size "
                    f"{tuple(voxel_size_mm)}; "
                    "it must be the acquired (k-space) resolution, >= the reported voxel"
                )
        else:
            fill = (1.0, 1.0)
        return PSF(self.kspace_filter, (max(fill[0], 1.0), max(fill[1], 1.0)))


def filter_weights(k, n_acquired: int, kind: str) -> np.ndarray:
    """The k-space filter ``w(k)`` at integer frequencies ``|k| <= n_acquired / 2``."""
    x = np.abs(np.asarray(k, dtype=float)) / (n_acquired / 2)
    if kind == "none":
        return np.ones_like(x)
    if kind == "hamming":
        return 0.54 + 0.46 * np.cos(np.pi * x)
    if kind == "tukey":
        taper = np.clip((x - TUKEY_FLAT) / (1 - TUKEY_FLAT), 0.0, 1.0)
        return 0.5 * (1 + np.cos(np.pi * taper))
    if kind == "fermi":
        return (1 + np.exp(-FERMI_RADIUS / FERMI_WIDTH)) / (1 + np.exp((x - FERMI_RADIUS) / FERMI_WIDTH))
    raise InputError(f"unknown k-space filter {kind!r}; choose from {', '.join(FILTERS)}")


def acquired_points(n: int, zero_fill: float) -> int:
    """``N = round(n / F)`` k-space samples of an axis with ``n`` reported points."""
    return max(1, int(round(n / zero_fill)))


def frequencies(n_acquired: int) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric frequencies ``k`` and the weights ``w'`` of the Nyquist split (1 elsewhere)."""
    half = n_acquired // 2
    k = np.arange(-half, half + 1)
    split = np.ones(k.size)
    if n_acquired % 2 == 0:
        split[[0, -1]] = 0.5
    return k, split


@dataclass(frozen=True)
class PSF:
    """Separable point-spread function of a Cartesian acquisition (see the module notes)."""

    filter: str = "none"
    zero_fill: tuple[float, float] = (1.0, 1.0)  # (y, x)
    choice: dict | None = field(default=None, compare=False, hash=False)  # how an "auto" filter was chosen

    def describe(self) -> dict:
        out = {"model": "kspace", "kspace_filter": self.filter, "zero_fill": list(self.zero_fill)}
        return out if self.choice is None else {**out, "filter_choice": self.choice}

    def kernel(self, n: int, spacing_mm: float, order: int, axis: int, rows=None, cols=None) -> np.ndarray:
        """``K[j, m]``: weight of fine point ``m`` (``order`` per voxel) in image point ``j`` of one axis.

        Notes
        -----
        ``K[j, m] = (Delta / L) sum_k w'(k) w(k) cos(2 pi k (x_j - xi_m) / L)`` with
        ``Delta = spacing / order`` the fine cell, ``L = n spacing`` and
        ``xi_m`` the midpoints of the fine cells (:func:`wss_nlp.models.measurement.subvoxel_offsets`);
        ``sum_m K[j, m] = w(0) = 1``. ``axis`` 0 is y, 1 is x; ``rows`` and
        ``cols`` select image points and fine points.
        """
        # K depends on t = j order - m alone, periodically in n order (x_j - xi_m = (t + (order - 1)/2) Delta):
        # one table per axis, cached, indexed for the rows and columns asked for
        table = _kernel_table(n, float(spacing_mm), int(order), float(self.zero_fill[axis]), self.filter)
        x = np.arange(n) if rows is None else np.asarray(rows, dtype=int)
        m = np.arange(n * order) if cols is None else np.asarray(cols, dtype=int)
        return table[(x[:, None] * order - m[None, :]) % (n * order)]


@functools.lru_cache(maxsize=64)
def _kernel_table(n: int, spacing_mm: float, order: int, zero_fill: float, filter_name: str) -> np.ndarray:
    """``K`` of :meth:`PSF.kernel` as a function of ``t = j order - m`` (``t = 0 .. n order - 1``)."""
    n_acq = acquired_points(n, zero_fill)
    k, split = frequencies(n_acq)
    wk = split * filter_weights(k, n_acq, filter_name)
    fov = n * spacing_mm
    d = (np.arange(n * order) + (order - 1) / 2) * spacing_mm / order
    arg = 2 * np.pi / fov * k
    return (spacing_mm / order / fov) * (np.cos(d[:, None] * arg) @ wk)


# ------------------------------------------------------------------ fine-grid averaging (velocity, dephasing)
class Averager:
    """PSF-weighted image values from values at the sub-voxel points of the lumen voxels.

    The box model's voxel mean over the voxel's own points becomes, for the
    k-space model, ``sum_p K_y(y_i - y_p) K_x(x_j - x_p) v_p`` over every
    point ``p`` of every lumen voxel (the whole lumen), computed as two
    dense products on the bounding box of the lumen's fine grid.

    Parameters
    ----------
    grid : wss_nlp.models.measurement.VoxelGrid
    index : (n_vox,) flat voxel indices (row-major) whose ``order x order`` points carry the values
    order : int
    psf : PSF
    out_index : flat indices of the voxels to report (default ``index``)
    """

    def __init__(self, grid, index: np.ndarray, order: int, psf: PSF, out_index=None):
        ny, nx = grid.shape
        iy, ix = np.divmod(np.asarray(index), nx)
        sub = np.arange(order)
        # fine row / column of every (voxel, point) in the voxel-major, row-major point order of subvoxel_points
        fy = (iy[:, None] * order + sub[None, :])[:, :, None].repeat(order, axis=2)
        fx = (ix[:, None] * order + sub[None, :])[:, None, :].repeat(order, axis=1)
        fy0, fx0 = int(fy.min()), int(fx.min())
        self.fy, self.fx = (fy - fy0).reshape(index.size, -1), (fx - fx0).reshape(index.size, -1)
        self.shape = (int(fy.max()) - fy0 + 1, int(fx.max()) - fx0 + 1)
        oy, ox = np.divmod(np.asarray(index if out_index is None else out_index), nx)
        rows_y, rows_x = np.unique(oy), np.unique(ox)
        self.out_y, self.out_x = np.searchsorted(rows_y, oy), np.searchsorted(rows_x, ox)
        self.ky = psf.kernel(ny, grid.dy, order, 0, rows_y, fy0 + np.arange(self.shape[0]))
        self.kx = psf.kernel(nx, grid.dx, order, 1, rows_x, fx0 + np.arange(self.shape[1]))

    def __call__(self, values: np.ndarray) -> np.ndarray:
        """``values`` of shape (n_vox, order^2[, k]) at the points -> (n_out[, k]) image values."""
        values = np.asarray(values)
        fine = np.zeros(self.shape + values.shape[2:], dtype=values.dtype)
        fine[self.fy, self.fx] = values
        out = np.tensordot(self.ky, fine, axes=(1, 0))  # (rows_y, fine_x, ...)
        out = np.tensordot(self.kx, np.moveaxis(out, 1, 0), axes=(1, 0))  # (rows_x, rows_y, ...)
        return out[self.out_x, self.out_y]

    def casadi(self, values):
        """The same map for a CasADi matrix of point values, (n_points, k) -> (n_out, k), points voxel-major.

        Notes
        -----
        Column ``j`` is scattered into the fine box ``F_j`` and mapped to
        ``K_y F_j K_x^T`` by :class:`SeparablePSF` (all columns as one batch
        of side-by-side blocks, BLAS, exact derivatives); the output voxels
        are then picked from the blocks. Cost about
        ``2 k (n_y n_fy n_fx + n_y n_fx n_x)`` flops.
        """
        n_fy, n_fx = self.shape
        n_ry, n_rx = self.ky.shape[0], self.kx.shape[0]
        k = values.shape[1]
        if getattr(self, "_casadi", None) is None:
            n_pts = self.fy.size
            flat = (self.fy + n_fy * self.fx).ravel()  # column-major position in the fine box, as CasADi stores
            scatter = ca.DM(ca.Sparsity.triplet(n_fy * n_fx, n_pts, flat.tolist(), list(range(n_pts))), np.ones(n_pts))
            self._casadi = (scatter, SeparablePSF(self.ky, self.kx), (self.out_y + n_ry * self.out_x).tolist())
        scatter, psf_map, rows = self._casadi
        fine = ca.reshape(ca.mtimes(scatter, values), n_fy, n_fx * k)  # block j = F_j
        blocks = psf_map.batched(k)(fine)  # (n_ry, n_rx k), block j = K_y F_j K_x^T
        return ca.reshape(blocks, n_ry * n_rx, k)[rows, :]


def signal_scale(raw: np.ndarray, background: float, moving: np.ndarray) -> float:
    """Least-squares ``rho`` in ``raw - background ~ rho |K chi e^{i theta}|`` over the voxels with ``moving > 1/2``.

    With a wide PSF the lumen's plateau itself dephases, so the histogram's
    plateau (Appendix B) underestimates ``rho``; the predicted ``moving``
    image fixes the scale.
    """
    use = moving > 0.5
    if not use.any():
        raise InputError("no voxel of the predicted lumen signal exceeds half the plateau; the vessel is unresolved")
    return float(np.sum(moving[use] * (raw[use] - background)) / np.sum(moving[use] ** 2))


def noise_correlation(n: int, zero_fill: float, kind: str, rows=None) -> np.ndarray:
    """Correlation of the image noise between points ``rows`` of one axis (unit diagonal).

    Notes
    -----
    White k-space noise, filtered by ``w`` and zero-filled, has in the image
    the covariance ``sigma^2 rho(x_i - x_j)`` per axis with
    ``rho(d) = sum_k w'(k) w(k)^2 cos(2 pi k d / L) / sum_k w'(k) w(k)^2``
    (symmetric frequencies, Nyquist split as in :meth:`PSF.kernel`): 1 on
    the diagonal; zero-filling (F > 1) and filters correlate neighbours.
    """
    table = _correlation_table(n, float(zero_fill), kind)  # rho depends on (i - j) mod n alone
    x = np.arange(n) if rows is None else np.asarray(rows, dtype=int)
    return table[(x[:, None] - x[None, :]) % n]


@functools.lru_cache(maxsize=32)
def _correlation_table(n: int, zero_fill: float, kind: str) -> np.ndarray:
    """``rho(t / n)`` of :func:`noise_correlation` for ``t = 0 .. n - 1`` (periodic in ``n``)."""
    n_acq = acquired_points(n, zero_fill)
    k, split = frequencies(n_acq)
    w2 = split * filter_weights(k, n_acq, kind) ** 2
    return np.cos(2 * np.pi * (np.arange(n) / n)[:, None] * k) @ w2 / np.sum(w2)


class NoiseCorrelation:
    """The image noise's correlation ``C = R_y (x) R_x`` on a set of voxels (:func:`noise_correlation`).

    ``apply(x)`` is ``C x`` for ``x`` of shape ``(n_vox, k)`` (two dense products on the voxels' bounding
    rows and columns); ``effective_fraction`` is the share of effectively independent samples,
    ``n_eff / n = 1 / (sum_d rho_y(d)^2 sum_d rho_x(d)^2)`` (Bretherton et al. 1999's
    ``tr(C)^2 / tr(C^2)`` of the periodic correlation): 1 for white noise, about ``1 / (F_y F_x)`` for
    zero-filling, less again with a filter (0.075 for Hamming with F = 2).
    """

    def __init__(self, shape: tuple[int, int], psf: PSF, index: np.ndarray):
        ny, nx = shape
        iy, ix = np.divmod(np.asarray(index), nx)
        self.rows, self.cols = np.unique(iy), np.unique(ix)
        self.at_y, self.at_x = np.searchsorted(self.rows, iy), np.searchsorted(self.cols, ix)
        full_y = noise_correlation(ny, psf.zero_fill[0], psf.filter)
        full_x = noise_correlation(nx, psf.zero_fill[1], psf.filter)
        self.ry, self.rx = full_y[np.ix_(self.rows, self.rows)], full_x[np.ix_(self.cols, self.cols)]
        self.effective_fraction = float(1.0 / (np.sum(full_y[0] ** 2) * np.sum(full_x[0] ** 2)))

    def apply(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        image = np.zeros((self.rows.size, self.cols.size) + x.shape[1:])
        image[self.at_y, self.at_x] = x
        out = np.tensordot(self.ry, image, axes=(1, 0))
        out = np.moveaxis(np.tensordot(self.rx, np.moveaxis(out, 1, 0), axes=(1, 0)), 0, 1)
        return out[self.at_y, self.at_x]


class AveragingOperator:
    """``A[i, p] = a_ip / s_i``: the k-space velocity operator's weights as a linear map from inside points to voxels.

    ``a_ip`` are the PSF weights of :class:`Averager` restricted to the lumen's
    inside points, ``s_i = sum_p a_ip`` the modeled signal; rows with ``keep``
    False are zero. ``A @ X`` and ``A.T @ y`` are evaluated with two dense
    products each (never the dense matrix); the pair passes a dot test
    (``tests/test_kspace.py``). Plays the role of
    :meth:`wss_nlp.models.measurement.LumenVoxels.mean_matrix` in the sensitivities.
    """

    def __init__(self, averager: Averager, inside: np.ndarray, signal: np.ndarray, keep: np.ndarray):
        self.averager, self.inside = averager, np.asarray(inside, bool)
        self.scale = np.where(keep, 1.0 / np.where(keep, signal, 1.0), 0.0)
        self.shape = (self.scale.size, int(self.inside.sum()))

    def __matmul__(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x)
        values = np.zeros(self.inside.shape + x.shape[1:], dtype=x.dtype)
        values[self.inside] = x
        out = self.averager(values)
        return out * self.scale.reshape((-1,) + (1,) * (out.ndim - 1))

    @property
    def T(self) -> _Adjoint:  # noqa: N802 (the numpy spelling of a transpose)
        return _Adjoint(self)


class _Adjoint:
    def __init__(self, op: AveragingOperator):
        self.op = op

    def __matmul__(self, y: np.ndarray) -> np.ndarray:
        op, av = self.op, self.op.averager
        y = np.asarray(y, dtype=float)
        extra = y.shape[1:]
        out = np.zeros((av.ky.shape[0], av.kx.shape[0]) + extra)
        np.add.at(out, (av.out_y, av.out_x), y * op.scale.reshape((-1,) + (1,) * len(extra)))
        fine = np.tensordot(av.ky.T, out, axes=(1, 0))  # (fine_y, rows_x, ...)
        fine = np.moveaxis(np.tensordot(av.kx.T, np.moveaxis(fine, 1, 0), axes=(1, 0)), 0, 1)  # (fine_y, fine_x)
        return fine[av.fy, av.fx][op.inside]


def window_index(grid, center, reach_mm: float, psf: PSF) -> np.ndarray:
    """Flat indices of the voxels within ``reach_mm`` plus ``WINDOW_ACQUIRED_VOXELS`` acquired voxels of ``center``."""
    xc, yc = grid.centers()
    dist = np.hypot(xc - center[0], yc - center[1]).ravel()
    return np.flatnonzero(dist <= reach_mm + WINDOW_ACQUIRED_VOXELS * max(psf.zero_fill) * grid.h)


def dephasing_correction(
    grid, voxels, velocity_at, venc: float, psf: PSF, out_index: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the phase variation does to a k-space image, predicted from a velocity reconstruction.

    Returns ``(still, moving, phase_error)``: ``still = |K chi|`` and
    ``moving = |K chi e^{i theta}|`` on the voxels ``out_index`` (the
    magnitude without and with the phase; their difference is what
    dephasing took from the magnitude), and
    ``phase_error = (venc / pi) arg(K chi e^{i theta}) - (K chi u) / (K chi)``
    on the lumen voxels, the difference between the measured phase and the
    linear velocity model of :func:`wss_nlp.models.velocity.assemble`
    (``theta = pi u / venc``).

    Notes
    -----
    The k-space counterpart of :func:`wss_nlp.models.measurement.dephasing_factors`:
    with the PSF every voxel mixes the phases of its neighbourhood (side lobes
    included), so the magnitude loss is added back, ``m + still - moving``,
    rather than divided out (a ratio is unstable where ringing crosses zero),
    and the
    velocity data become ``u - phase_error``, which the linear model then
    fits exactly at the predicting velocity (one fixed-point step of the
    nonlinear phase model). ``voxels`` are the lumen voxels
    (:class:`wss_nlp.models.measurement.LumenVoxels`); ``velocity_at(x, y)`` gives
    m/s at points in mm.
    """
    order = int(round(np.sqrt(voxels.px.shape[1])))
    u = np.zeros(voxels.px.shape)
    u[voxels.inside] = velocity_at(voxels.px[voxels.inside], voxels.py[voxels.inside])
    chi = voxels.inside.astype(float)
    theta = np.pi * u / venc
    parts = np.stack([chi, chi * np.cos(theta), chi * np.sin(theta), chi * u], axis=-1)
    everywhere = np.union1d(out_index, voxels.index)
    image = Averager(grid, voxels.index, order, psf, everywhere)(parts)
    at_out, at_lumen = np.searchsorted(everywhere, out_index), np.searchsorted(everywhere, voxels.index)
    still, moving = np.abs(image[at_out, 0]), np.hypot(image[at_out, 1], image[at_out, 2])
    lum = image[at_lumen]
    signal = np.where(np.abs(lum[:, 0]) > 1e-12, lum[:, 0], 1.0)
    # arg relative to the sign of the signal: where ringing makes K chi negative the phase turns by pi
    phase = np.angle((lum[:, 1] + 1j * lum[:, 2]) * np.sign(signal))
    return still, moving, venc / np.pi * phase - lum[:, 3] / signal


# ------------------------------------------------------------------ the separable PSF as a CasADi operation
class SeparablePSF(ca.Callback):
    """``X -> K_y X_j K_x^T`` for each of ``blocks`` side-by-side blocks ``X_j``, as a CasADi function.

    A linear map evaluated by two BLAS products (CasADi's own dense
    products are plain loops, about 10x slower at these sizes), with exact
    derivatives of every order: the forward derivative of a linear map is the
    map on the seeds (all directions as one batch of blocks), the reverse one
    its adjoint ``Y -> K_y^T Y_j K_x`` (:attr:`adjoint`). Keep a reference to
    the instance while functions built from it live (CasADi's rule for
    callbacks); derived maps are kept by their parent.
    """

    def __init__(self, ky: np.ndarray, kx: np.ndarray, blocks: int = 1, adjoint: bool = False):
        ca.Callback.__init__(self)
        self.ky, self.kx, self.blocks, self.adjoint = np.asarray(ky), np.asarray(kx), int(blocks), adjoint
        self._derived: dict = {}
        (ry, fy), (rx, fx) = self.ky.shape, self.kx.shape
        self.shape_in = (ry, rx) if adjoint else (fy, fx)
        self.shape_out = (fy, fx) if adjoint else (ry, rx)
        self.construct(f"psf_{'adj' if adjoint else 'fwd'}_{blocks}", {})

    def get_n_in(self):
        return 1

    def get_n_out(self):
        return 1

    def get_sparsity_in(self, i):
        return ca.Sparsity.dense(self.shape_in[0], self.shape_in[1] * self.blocks)

    def get_sparsity_out(self, i):
        return ca.Sparsity.dense(self.shape_out[0], self.shape_out[1] * self.blocks)

    def apply(self, x: np.ndarray) -> np.ndarray:
        """The map on a NumPy array of ``blocks`` side-by-side blocks."""
        left, right = (self.ky.T, self.kx.T) if self.adjoint else (self.ky, self.kx)
        k, m_in = self.blocks, self.shape_in[1]
        rows = np.ascontiguousarray(left @ x)  # (out rows, blocks * m_in), one product for all blocks
        # block j of a row is rows[r, j m_in : (j + 1) m_in]: all blocks of all rows as one product
        out = rows.reshape(-1, m_in) @ right.T
        return out.reshape(rows.shape[0], k * right.shape[0])

    def has_eval_buffer(self):
        return True

    def eval_buffer(self, arg, res):
        # CasADi's own memory (column-major), read and written in place: no conversion of the images
        n_in, n_out = self.shape_in[0], self.shape_out[0]
        x = np.frombuffer(arg[0], dtype=np.float64).reshape(-1, n_in).T
        out = np.frombuffer(res[0], dtype=np.float64).reshape(-1, n_out).T
        out[...] = self.apply(x)
        return 0

    def batched(self, blocks: int, adjoint: bool = False) -> SeparablePSF:
        """The map (or its adjoint) on ``blocks`` side-by-side blocks, built once and kept by this instance."""
        key = (blocks, adjoint)
        if key not in self._derived:
            self._derived[key] = SeparablePSF(self.ky, self.kx, blocks, adjoint)
        return self._derived[key]

    def has_forward(self, nfwd):
        return True

    def get_forward(self, nfwd, name, inames, onames, opts):
        x, y = ca.MX.sym("x", self.sparsity_in(0)), ca.MX.sym("y", self.sparsity_out(0))
        seed = ca.MX.sym("seed", self.shape_in[0], self.shape_in[1] * self.blocks * nfwd)
        out = self.batched(self.blocks * nfwd, self.adjoint)(seed)
        return ca.Function(name, [x, y, seed], [out], inames, onames, opts)

    def has_reverse(self, nadj):
        return True

    def get_reverse(self, nadj, name, inames, onames, opts):
        x, y = ca.MX.sym("x", self.sparsity_in(0)), ca.MX.sym("y", self.sparsity_out(0))
        seed = ca.MX.sym("seed", self.shape_out[0], self.shape_out[1] * self.blocks * nadj)
        out = self.batched(self.blocks * nadj, not self.adjoint)(seed)
        return ca.Function(name, [x, y, seed], [out], inames, onames, opts)


# ------------------------------------------------------------------ geometry: |PSF * H_gamma(R - |x|)|
@dataclass
class KSpaceMagnitudeModel:
    """The fine-grid pieces of the k-space magnitude model of one slice (see :func:`magnitude_model`).

    ``annulus`` (the voxels whose magnitude enters the fit, named as in
    :class:`wss_nlp.models.measurement.AnnulusModel`) and ``inside`` (voxels inside
    every admissible lumen and outside the window) keep the box model's
    meaning for the callers.
    """

    annulus: np.ndarray
    inside: np.ndarray
    rho: np.ndarray  # (n_free,) distance of the free fine points to the centre
    phi: np.ndarray  # (n_free,) their polar angles
    x: np.ndarray  # (n_free,) their coordinates relative to the centre, mm
    y: np.ndarray
    free: np.ndarray  # (n_free,) their flat indices in the fine bounding box (column-major: x fastest is y)
    constant: np.ndarray  # (fine_y, fine_x) 1 inside r0, 0 elsewhere
    ky: np.ndarray  # (window rows, fine_y)
    kx: np.ndarray  # (window cols, fine_x)
    select: np.ndarray  # flat (column-major) positions of the annulus voxels in the (rows, cols) block
    order: int
    operator: SeparablePSF | None = None  # K_y . K_x^T as a CasADi operation (built on first symbolic use)
    # the radius basis at the free points as BLAS maps (radius values; scattered Jacobian columns), per size of c
    basis_ops: dict = field(default_factory=dict)

    def basis_maps(self, n_fourier: int):
        """``c -> R(phi_j)`` at the free points and the scattered columns ``s -> [P diag(s) b_j]_j`` (kept here)."""
        if n_fourier not in self.basis_ops:
            design = rad.design_matrix(self.phi, n_fourier)
            self.basis_ops[n_fourier] = (
                operators.MatrixProduct(design),
                operators.ScatteredBlocks(design, self.free, self.constant.shape),
            )
        return self.basis_ops[n_fourier]


def magnitude_setup(grid, center, r0: float, r1: float, order: int, gamma: float, psf: PSF) -> KSpaceMagnitudeModel:
    """Split the fine grid into constant and radius-dependent points and build the window's kernels.

    Fine points farther than ``6 gamma`` inside ``r0`` are 1, farther than
    ``6 gamma`` outside ``r1`` are 0 (``H_gamma`` within 1e-16 of its
    limits); the window is every voxel whose centre lies within
    ``WINDOW_ACQUIRED_VOXELS`` acquired voxels of the annulus ``[r0, r1]``.
    """
    ny, nx = grid.shape
    margin_fine = 6 * gamma + 0.5 * grid.h
    reach = r1 + margin_fine
    fine_y = (np.arange(ny * order) + 0.5) * grid.dy / order - 0.5 * grid.dy + grid.origin_mm[1]
    fine_x = (np.arange(nx * order) + 0.5) * grid.dx / order - 0.5 * grid.dx + grid.origin_mm[0]
    cols_f = np.flatnonzero(np.abs(fine_x - center[0]) <= reach)
    rows_f = np.flatnonzero(np.abs(fine_y - center[1]) <= reach)
    if cols_f.size == 0 or rows_f.size == 0:
        raise InputError("the geometry box lies outside the image")
    fx, fy = np.meshgrid(fine_x[cols_f] - center[0], fine_y[rows_f] - center[1])
    rho = np.hypot(fx, fy)
    constant = (rho < r0 - 6 * gamma).astype(float)
    free = np.flatnonzero(((rho >= r0 - 6 * gamma) & (rho <= r1 + 6 * gamma)).T)  # column-major, as CasADi's reshape
    rho_t, phi_t = rho.T.ravel()[free], np.arctan2(fy, fx).T.ravel()[free]
    x_t, y_t = fx.T.ravel()[free], fy.T.ravel()[free]

    xc, yc = grid.centers()
    dist = np.hypot(xc - center[0], yc - center[1]).ravel()
    margin = WINDOW_ACQUIRED_VOXELS * max(psf.zero_fill) * grid.h
    window = np.flatnonzero((dist >= r0 - margin) & (dist <= r1 + margin))
    inside = np.flatnonzero(dist < r0 - margin)
    iy, ix = np.divmod(window, nx)
    rows, cols = np.unique(iy), np.unique(ix)
    ky = psf.kernel(ny, grid.dy, order, 0, rows, rows_f)
    kx = psf.kernel(nx, grid.dx, order, 1, cols, cols_f)
    # the block is (rows, cols); CasADi stores it column-major
    select = np.searchsorted(cols, ix) * rows.size + np.searchsorted(rows, iy)
    return KSpaceMagnitudeModel(window, inside, rho_t, phi_t, x_t, y_t, free, constant, ky, kx, select, order)


def magnitude_model(
    model: KSpaceMagnitudeModel,
    coefficients,
    gamma,
    heaviside: str = "erf",
    shift=None,
    jacobian: bool = False,
    second_order: bool = False,
):
    """``|K_y H K_x^T|`` on the window voxels: the k-space counterpart of eq. (discForw) (CasADi or NumPy).

    Notes
    -----
    ``H`` is the fine image of ``H_gamma(R(phi) - |xi|)`` (constant where it
    does not depend on R); the magnitude is ``sqrt(I^2 + eps^2)`` with
    ``eps`` = :data:`ABS_SMOOTHING`, smooth where Gibbs ringing crosses zero.
    Cost per evaluation about ``2 n_w n_f^2`` flops for ``n_w`` window rows
    and ``n_f`` fine rows. ``shift`` (CasADi, 2 entries) moves the centre of
    ``R`` by that much (mm): the polar coordinates of the free points become
    symbolic, so derivatives in the centre are exact (the sensitivities).

    ``jacobian=True`` (symbolic, no ``shift``) returns ``(F, dF/dc)`` with the
    PSF applied by :class:`SeparablePSF` (BLAS) and the Jacobian assembled by
    the chain rule, ``dF/dc = (I / F) K_y (H' b_j) K_x^T`` for the radius basis
    functions ``b_j``, all ``j`` in one batched call: the solver's
    Gauss-Newton form. Without it the PSF products are CasADi's own, which
    every other derivative (Hessians, parameter derivatives) goes through;
    both are the same function (``tests/test_kspace.py``).

    ``second_order`` (with ``jacobian``) also returns ``w -> sum_i w_i
    d^2F_i/dc^2`` for an ``MX`` column ``w`` over the window voxels, the
    second-order term of a least-squares Hessian: with the filtered signal
    ``I``, ``F = sqrt(I^2 + eps^2)`` and ``I_i = sum_j K_ij H_gamma(b_j^T c -
    rho_j)``, ``sum_i w_i Hess F_i = dI^T diag(w eps^2 / F^3) dI + B^T
    diag(d) B`` with ``d_j = H_gamma''_j (K^T (w I / F))_j``: the adjoint
    PSF once, then the weighted Gram matrix of the radius basis at the free
    points (:func:`wss_nlp.models.measurement.weighted_gram`).
    """
    from .measurement import gram_pieces, heaviside_curvature, heaviside_slope, smoothed_heaviside, weighted_gram

    symbolic = isinstance(coefficients, (ca.MX, ca.SX))
    n = rad.n_fourier_from_size(coefficients.numel() if symbolic else np.size(coefficients))
    fy, fx = model.constant.shape
    if symbolic:
        if shift is None and isinstance(coefficients, ca.MX):
            radius, rho = model.basis_maps(n)[0](coefficients), ca.DM(model.rho)
        elif shift is None:
            radius, rho = ca.mtimes(ca.DM(rad.design_matrix(model.phi, n)), coefficients), ca.DM(model.rho)
        else:
            dx, dy = ca.DM(model.x) - shift[0], ca.DM(model.y) - shift[1]
            rho, phi = ca.sqrt(dx * dx + dy * dy), ca.atan2(dy, dx)
            cos = [ca.cos(k * phi) for k in range(1, n + 1)]
            sin = [ca.sin(k * phi) for k in range(1, n + 1)]
            radius = ca.mtimes(ca.horzcat(ca.DM.ones(model.x.size), *cos, *sin), coefficients)
        vals = smoothed_heaviside(radius - rho, gamma, heaviside)
        scatter = ca.DM(
            ca.Sparsity.triplet(fy * fx, model.free.size, model.free.tolist(), list(range(model.free.size))),
            np.ones(model.free.size),
        )
        fine = ca.reshape(ca.DM(model.constant.T.ravel()) + ca.mtimes(scatter, vals), fy, fx)
        if not jacobian:
            image = ca.mtimes(ca.mtimes(ca.DM(model.ky), fine), ca.DM(model.kx.T))
            signal = ca.vec(image)[model.select.tolist()]
            return ca.sqrt(signal * signal + ABS_SMOOTHING**2)
        if shift is not None:
            raise InputError("magnitude_model: jacobian=True takes no centre shift")
        if model.operator is None:
            model.operator = SeparablePSF(model.ky, model.kx)
        signal = ca.vec(model.operator(fine))[model.select.tolist()]
        magnitude = ca.sqrt(signal * signal + ABS_SMOOTHING**2)
        n_c = coefficients.numel()
        # d vals / d c_j = H'(R - rho) b_j(phi): every column scattered into the fine box, side by side (BLAS)
        slope = heaviside_slope(radius - rho, gamma, heaviside)  # H' at each free point
        if isinstance(coefficients, ca.MX):
            columns = model.basis_maps(n)[1](slope)  # (fy, fx n_c)
        else:
            columns = ca.reshape(
                ca.mtimes(scatter, ca.repmat(slope, 1, n_c) * ca.DM(rad.design_matrix(model.phi, n))), fy, fx * n_c
            )
        blocks = model.operator.batched(n_c)(columns)
        rows, cols = model.ky.shape[0], model.kx.shape[0]
        d_signal = ca.reshape(blocks, rows * cols, n_c)[model.select.tolist(), :]
        d_magnitude = ca.repmat(signal / magnitude, 1, n_c) * d_signal
        if not second_order:
            return magnitude, d_magnitude
        if not isinstance(coefficients, ca.MX):
            raise InputError("magnitude_model: second_order=True takes MX coefficients")
        key = ("gram", n)
        if key not in model.basis_ops:
            model.basis_ops[key] = gram_pieces(model.basis_maps(n)[0], n)
        pieces, adjoint = model.basis_ops[key], model.operator.batched(1, adjoint=True)
        window = ca.DM(
            ca.Sparsity.triplet(rows * cols, model.select.size, model.select.tolist(), list(range(model.select.size))),
            np.ones(model.select.size),
        )
        curvature = heaviside_curvature(radius - rho, gamma, heaviside)

        def second(weights):
            w = ca.vec(weights)
            outer = ca.mtimes(d_signal.T, ca.repmat(w * ABS_SMOOTHING**2 / magnitude**3, 1, n_c) * d_signal)
            back = adjoint(ca.reshape(ca.mtimes(window, w * signal / magnitude), rows, cols))  # K^T (w I / F)
            return outer + weighted_gram(pieces, ca.mtimes(scatter.T, ca.vec(back)) * curvature)

        return magnitude, d_magnitude, second
    basis = rad.design_matrix(model.phi, n)
    vals = smoothed_heaviside(basis @ np.asarray(coefficients, dtype=float) - model.rho, gamma, heaviside)
    flat = model.constant.T.ravel().copy()
    flat[model.free] += vals
    fine = flat.reshape(fx, fy).T
    image = model.ky @ fine @ model.kx.T
    signal = image.T.ravel()[model.select]
    return np.sqrt(signal**2 + ABS_SMOOTHING**2)


# ------------------------------------------------------------------ phantoms: acquisition in k-space
def acquire(
    signal_at, grid, psf: PSF, snr: float | None, rng: np.random.Generator, rho: float = 1.0, spacing_mm: float = 0.025
) -> np.ndarray:
    """Complex image of a Cartesian acquisition of ``signal_at`` (independent of :meth:`PSF.kernel`).

    Notes
    -----
    The signal is sampled at the midpoints of ``S x S`` cells per voxel
    (``S = clip(ceil(h / spacing), 4, 40)``); its DFT, shifted to the
    voxel-centre origin, approximates the continuous Fourier transform at the
    acquired frequencies ``-N/2 <= k < N/2`` (the scanner's asymmetric
    sampling). These are filtered, zero-filled to ``n`` and inverse
    transformed. Noise: white complex noise of standard deviation
    ``rho / snr`` per channel in the image reconstructed at the acquired
    resolution without filter, added in k-space (so filtering lowers it and
    zero-filling correlates it, as on a scanner).

    Parameters
    ----------
    signal_at : callable
        ``(x, y) -> complex signal`` at physical points (mm), arrays of one shape.
    """
    ny, nx = grid.shape
    s = int(np.clip(np.ceil(grid.h / spacing_mm), 4, 40))
    fine_y = grid.origin_mm[1] + (np.arange(ny * s) + 0.5) * grid.dy / s - 0.5 * grid.dy
    fine_x = grid.origin_mm[0] + (np.arange(nx * s) + 0.5) * grid.dx / s - 0.5 * grid.dx
    spectrum = np.zeros((ny * s, nx * s), dtype=complex)
    for start in range(0, ny * s, 256):  # row blocks keep memory small at fine resolution
        py, px = np.meshgrid(fine_y[start : start + 256], fine_x, indexing="ij")
        spectrum[start : start + 256] = signal_at(px, py)
    spectrum = np.fft.fft2(spectrum)
    out = np.zeros((ny, nx), dtype=complex)
    n_acq = (acquired_points(ny, psf.zero_fill[0]), acquired_points(nx, psf.zero_fill[1]))
    k = [np.arange(-(na // 2), na - na // 2) for na in n_acq]  # the scanner's -N/2 <= k < N/2
    # fine cell midpoints sit delta = (1/S - 1)/2 voxel from the voxel centres: shift the phase back
    shift = [np.exp(-2j * np.pi * kk * (0.5 / s - 0.5) / n) for kk, n in zip(k, (ny, nx))]
    block = spectrum[np.ix_(k[0] % (ny * s), k[1] % (nx * s))] * np.outer(shift[0], shift[1]) / (s * s)
    if snr is not None:
        noise = rho / snr * (rng.standard_normal(n_acq) + 1j * rng.standard_normal(n_acq))
        block = block + np.fft.fft2(noise)[np.ix_(k[0] % n_acq[0], k[1] % n_acq[1])] * (ny * nx) / (n_acq[0] * n_acq[1])
    block = block * np.outer(filter_weights(k[0], n_acq[0], psf.filter), filter_weights(k[1], n_acq[1], psf.filter))
    out[np.ix_(k[0] % ny, k[1] % nx)] = block
    return np.fft.ifft2(out)
