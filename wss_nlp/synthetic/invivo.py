"""In-vivo-like phantoms: the 2D vessels of :mod:`wss_nlp.synthetic.phantoms` in tissue, with exact truth.

A patient's slice is not a lumen in air. :func:`make_invivo` places the laminar (Poiseuille, elliptic
pipe) or turbulent (DNS mean profile, Re_tau 180.9) vessel of :func:`wss_nlp.synthetic.phantoms.make_phantom`
in a 64 x 64 mm view with

* a **vessel wall** ring (1.2 mm, darker than the tissue),
* **textured tissue** of intermediate signal (a smooth random field, about 20 % contrast, 2-6 mm features),
* **fat** (bright, static): a subcutaneous layer under the body surface and two small deposits, and on request
  (``touching_fat``) deposits pressed against the vessel's wall, which join the lumen in one bright region of
  the magnitude (only the velocity tells them apart),
* **air** above the body surface (no signal),
* **neighbouring vessels** with their own flow: an artery (forward) and a vein (reverse flow), each with a wall,
* an **eddy-current phase offset** over the whole view (linear, quadratic or a smooth non-polynomial field)
  of ``offset_pct`` percent of the venc at the vessel's centre,
* **inflow enhancement** of the lumen signal (``1 + 0.2 |u| / u_peak``: fresh spins are brighter) and
* **coil shading** (a smooth multiplicative field, about +-20 % across the view).

Each voxel holds the complex signal ``rho(x) exp(i pi (u(x) + o(x)) / venc)`` averaged over the voxel
(midpoint rule, points at most 0.04 mm apart), so partial-volume voxels mix lumen, wall and tissue with
their own phases, as :func:`wss_nlp.synthetic.phantoms.acquire` does for the lumen alone; then complex
Gaussian noise of ``1 / snr`` per channel (the lumen's base signal is 1).

The truth is computed from the analytic description only (the flows' exact WSS, the offset function,
the region indicators), never with the reconstruction code. ``surround=False`` gives the same vessel on the
same grid, offset and noise seed in air (no wall, tissue, fat, neighbours, offset, inflow or shading):
the reference every in-tissue error is compared with (``scripts/invivo.py``).

Development seeds (:data:`DEV_SEEDS`) tune; the tables use :data:`REPORTED_SEEDS` only.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

import numpy as np

from ..errors import InputError
from ..io.files import Acquisition
from ..models.measurement import VoxelGrid
from .phantoms import (
    Circle,
    Ellipse,
    Flow,
    PoiseuilleEllipse,
    StarPoiseuille,
    Truth,
    TurbulentPipe,
    complex_noise,
    peak_velocity,
)

#: Side of the square field of view, mm.
VIEW_MM = 64.0
#: Seeds to tune on (never in a reported table).
DEV_SEEDS = (101, 102, 103, 104, 105)
#: Seeds of the reported tables (``scripts/invivo.py``).
REPORTED_SEEDS = (201, 202, 203, 204, 205)
#: The eddy-current offset fields; seed ``s`` takes ``OFFSET_FAMILIES[s % 3]`` unless one is named.
OFFSET_FAMILIES = ("linear", "quadratic", "smooth")

#: Signal levels relative to the lumen's base signal (1): wall, mean tissue, fat.
WALL_LEVEL, TISSUE_LEVEL, FAT_LEVEL = 0.22, 0.32, 0.80
#: Wall thickness of the main vessel and of the neighbours, mm.
WALL_MM, NEIGHBOUR_WALL_MM = 1.2, 0.6
#: Relative standard deviation of the tissue texture.
TEXTURE = 0.2
#: Inflow enhancement at the peak speed: ``rho = 1 + INFLOW |u| / u_peak`` in a lumen.
INFLOW = 0.2
#: Fat deposits touching the main vessel (``touching_fat``): radius, and their centres' distance beyond the wall
#: ``R(phi)`` (mm; less than the radius: each reaches the wall ring's outer edge, the wall and lumen take
#: precedence), and the angle of the first (rad; the others equally spaced).
TOUCHING_FAT_MM, TOUCHING_FAT_BEYOND_MM, TOUCHING_FAT_ANGLE = 5.0, 4.0, 0.3


@dataclass(frozen=True)
class Surroundings:
    """What the tissue around the vessels looks like (the signal levels relative to the lumen's base signal 1).

    :data:`TEXTURED` is the in-vivo-like default; :data:`UNIFORM` the same without texture (a uniform tissue:
    its outside ring is one level within the noise, but the wall ring and the lumen's inflow and shading are
    still there); :data:`BATH` the two-level case in tissue (one level outside and in the wall, a uniform lumen,
    no shading): what Appendix B's model describes exactly.
    """

    texture: float = TEXTURE  # relative standard deviation of the tissue texture
    wall_level: float = WALL_LEVEL  # of the vessels' wall rings
    inflow: float = INFLOW  # the lumens' inflow enhancement at the peak speed
    shading: bool = True  # coil shading over the view


TEXTURED = Surroundings()
UNIFORM = Surroundings(texture=0.0)
BATH = Surroundings(texture=0.0, wall_level=TISSUE_LEVEL, inflow=0.0, shading=False)

#: Largest midpoint spacing of the voxel means, mm, and the most points per voxel axis.
SPACING_MM, MAX_POINTS = 0.04, 40


def _main_flow(case: str) -> Flow:
    """The vessel of ``make_phantom(case)`` (same lumen and flow), centre set later."""
    if case == "laminar":
        return PoiseuilleEllipse(lumen=Ellipse(a=13.0, b=10.0, angle=0.4), viscosity_pa_s=3.5e-3, u_max=0.4)
    if case == "turbulent":
        return TurbulentPipe(lumen=Circle(r=25.885 / 2), viscosity_pa_s=0.955e-3)
    raise InputError(f"unknown in-vivo phantom case {case!r}; choose laminar or turbulent")


def _outer_inside(lumen, x, y, thickness: float) -> np.ndarray:
    """Points within ``thickness`` mm outside a lumen's wall (radially, about its centre): the wall ring."""
    dx, dy = np.asarray(x) - lumen.center[0], np.asarray(y) - lumen.center[1]
    r = np.hypot(dx, dy)
    big_r = lumen.radius(np.arctan2(dy, dx)).reshape(np.shape(dx))
    return (r >= big_r) & (r < big_r + thickness)


@dataclass
class OffsetField:
    """The eddy-current velocity offset ``o(x, y) = scale g(xi, eta)`` in m/s with ``g(0, 0) = 1``.

    ``xi = (x - x_c) / 32 mm``, ``eta = (y - y_c) / 32 mm`` about the main vessel's centre ``(x_c, y_c)``;
    ``scale = offset_pct / 100 venc``. Families: "linear" ``1 + a1 xi + a2 eta``; "quadratic" adds
    ``b1 xi^2 + b2 xi eta + b3 eta^2``; "smooth" ``1 + 0.6 (s(xi, eta) - s(0, 0)) + 0.5 (G(xi, eta) - G(0, 0))``
    with ``s = sin(2.2 xi + p1) sin(1.7 eta + p2)`` and a Gaussian bump ``G`` of width 0.6 (not a polynomial).
    """

    family: str
    scale: float  # m/s at the vessel centre
    center: tuple[float, float]
    a: tuple = (0.0, 0.0)
    b: tuple = (0.0, 0.0, 0.0)
    p: tuple = (0.0, 0.0)
    bump: tuple = (0.0, 0.0)

    def _g(self, xi, eta):
        if self.family == "none":
            return np.zeros_like(xi)
        g = 1.0 + self.a[0] * xi + self.a[1] * eta
        if self.family == "quadratic":
            g = g + self.b[0] * xi**2 + self.b[1] * xi * eta + self.b[2] * eta**2
        if self.family == "smooth":
            g = 1.0 + 0.6 * (
                np.sin(2.2 * xi + self.p[0]) * np.sin(1.7 * eta + self.p[1]) - np.sin(self.p[0]) * np.sin(self.p[1])
            )

            def bump(u, v):
                return np.exp(-((u - self.bump[0]) ** 2 + (v - self.bump[1]) ** 2) / 0.36)

            g = g + 0.5 * (bump(xi, eta) - bump(0.0, 0.0))
        return g

    def __call__(self, x, y) -> np.ndarray:
        xi = (np.asarray(x, float) - self.center[0]) / 32.0
        eta = (np.asarray(y, float) - self.center[1]) / 32.0
        return self.scale * self._g(xi, eta)


@dataclass
class Scene:
    """The continuous in-vivo-like slice: regions, signal density and phase at any point (mm)."""

    main: Flow
    neighbours: tuple = ()  # flows of the other vessels (their lumens Circles)
    venc: float = 1.0
    surround: bool = True
    offset: OffsetField | None = None
    u_peak: float = 1.0  # of the main vessel, for the inflow enhancement
    texture_k: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # wave vectors, rad/mm
    texture_phase: np.ndarray = field(default_factory=lambda: np.zeros(0))
    shading: tuple = (0.0, 0.0, 0.0)  # coil shading exp(c0 xi + c1 eta + c2 (xi^2 + eta^2)), view coordinates
    surroundings: Surroundings = TEXTURED
    fat_blobs: tuple = ()  # (x, y, r) mm
    surface: tuple = (24.0, 3.0, 9.0)  # body surface y = s0 + s1 sin(x / s2); air above
    fat_layer_mm: float = 6.0

    def _surface(self, x):
        return self.surface[0] + self.surface[1] * np.sin(np.asarray(x) / self.surface[2])

    def regions(self, x, y) -> dict:
        """Boolean indicators of each region at points (mutually exclusive, by precedence)."""
        lumen = self.main.lumen.inside(x, y)
        out = {"lumen": lumen}
        if not self.surround:
            return out
        taken = lumen.copy()
        for k, f in enumerate(self.neighbours):
            inside = f.lumen.inside(x, y) & ~taken
            out[f"neighbour{k}"] = inside
            taken |= inside
        wall = _outer_inside(self.main.lumen, x, y, WALL_MM) & ~taken
        for f in self.neighbours:
            wall |= _outer_inside(f.lumen, x, y, NEIGHBOUR_WALL_MM) & ~taken
        out["wall"] = wall
        taken |= wall
        surf = self._surface(x)
        air = (np.asarray(y) > surf) & ~taken
        out["air"] = air
        taken |= air
        fat = (np.asarray(y) > surf - self.fat_layer_mm) & ~taken
        for bx, by, br in self.fat_blobs:
            fat |= (np.hypot(np.asarray(x) - bx, np.asarray(y) - by) < br) & ~taken
        out["fat"] = fat
        taken |= fat
        out["tissue"] = ~taken
        return out

    def texture(self, x, y) -> np.ndarray:
        """``1 + texture T(x, y)``, T a unit-variance sum of random plane waves (:attr:`Surroundings.texture`)."""
        if self.texture_k.size == 0:
            return np.ones(np.shape(x))
        arg = np.multiply.outer(np.asarray(x), self.texture_k[:, 0]) + np.multiply.outer(
            np.asarray(y), self.texture_k[:, 1]
        )
        t = np.sqrt(2.0 / self.texture_k.shape[0]) * np.cos(arg + self.texture_phase).sum(axis=-1)
        return 1.0 + self.surroundings.texture * t

    def coil(self, x, y) -> np.ndarray:
        xi, eta = np.asarray(x) / 32.0, np.asarray(y) / 32.0
        c = self.shading
        return np.exp(c[0] * xi + c[1] * eta + c[2] * (xi**2 + eta**2))

    def velocity(self, x, y, regions=None) -> np.ndarray:
        """Through-plane blood velocity (m/s), zero in static tissue."""
        reg = self.regions(x, y) if regions is None else regions
        u = np.where(reg["lumen"], self.main.velocity(x, y), 0.0)
        for k, f in enumerate(self.neighbours):
            u = u + np.where(reg[f"neighbour{k}"], f.velocity(x, y), 0.0)
        return u

    def signal(self, x, y) -> np.ndarray:
        """The complex signal ``rho exp(i pi (u + o) / venc)`` at points."""
        reg = self.regions(x, y)
        u = self.velocity(x, y, reg)
        if not self.surround:
            return reg["lumen"] * np.exp(1j * np.pi * u / self.venc)
        flowing = reg["lumen"].copy()
        for k in range(len(self.neighbours)):
            flowing |= reg[f"neighbour{k}"]
        look = self.surroundings
        rho = np.where(flowing, 1.0 + look.inflow * np.abs(u) / self.u_peak, 0.0)
        rho = rho + look.wall_level * reg["wall"] + FAT_LEVEL * reg["fat"]
        tissue = reg["tissue"]
        if tissue.any():
            tex = np.ones(np.shape(x))
            tex[tissue] = self.texture(np.asarray(x)[tissue], np.asarray(y)[tissue])
            rho = rho + TISSUE_LEVEL * tissue * tex
        rho = rho * self.coil(x, y)
        phase = u + (0.0 if self.offset is None else self.offset(x, y))
        return rho * np.exp(1j * np.pi * phase / self.venc)


@dataclass
class InvivoTruth(Truth):
    """A :class:`~wss_nlp.synthetic.phantoms.Truth` of the main vessel, and what the scene around it holds."""

    scene: Scene | None = None
    grid: VoxelGrid | None = None
    static_fraction: np.ndarray | None = None  # (ny, nx) voxel fraction of static tissue with signal
    flowing_fraction: np.ndarray | None = None  # (ny, nx) voxel fraction of any lumen (main or neighbour)

    def offset_at(self, x, y) -> np.ndarray:
        """The true velocity offset (m/s) at points (0 without one)."""
        o = None if self.scene is None else self.scene.offset
        return np.zeros(np.shape(x)) if o is None else o(x, y)

    def lumen_mask(self) -> np.ndarray:
        """Voxels whose centre lies in the main lumen."""
        assert self.grid is not None
        xc, yc = self.grid.centers()
        return self.flow.lumen.inside(xc, yc)


def _touching_fat(lumen, n: int) -> tuple:
    """``n`` fat deposits (x, y, r) pressed against the lumen's wall (:data:`TOUCHING_FAT_MM`), no random draw."""
    out = []
    for k in range(n):
        phi = TOUCHING_FAT_ANGLE + 2 * np.pi * k / n
        d = float(lumen.radius(np.array([phi]))[0]) + TOUCHING_FAT_BEYOND_MM
        out.append((lumen.center[0] + d * np.cos(phi), lumen.center[1] + d * np.sin(phi), TOUCHING_FAT_MM))
    return tuple(out)


def _scene(
    case: str,
    rng: np.random.Generator,
    h_mm: float,
    surround: bool,
    offset_pct: float,
    family,
    touching_fat: int = 0,
    surroundings: Surroundings = TEXTURED,
) -> Scene:
    main = _main_flow(case)
    shift = rng.uniform(-0.5, 0.5, size=2) * h_mm
    center = (-3.0 + float(shift[0]), -4.0 + float(shift[1]))
    main.lumen.center = center
    # everything below is drawn whether or not it is used: the noise of the air twin is the same draw
    jitter = rng.uniform(-1.0, 1.0, size=8)
    n_waves = 40
    kmag = rng.uniform(2 * np.pi / 6.0, 2 * np.pi / 2.0, size=n_waves)
    kang = rng.uniform(0, 2 * np.pi, size=n_waves)
    k = np.stack([kmag * np.cos(kang), kmag * np.sin(kang)], axis=1)
    kphase = rng.uniform(0, 2 * np.pi, size=n_waves)
    shading = (0.25 * jitter[0], 0.2 * jitter[1], -0.15 + 0.05 * jitter[2]) if surroundings.shading else (0.0,) * 3
    a = tuple(0.8 * rng.uniform(-1, 1, size=2))
    b = tuple(0.6 * rng.uniform(-1, 1, size=3))
    p = tuple(rng.uniform(0, 2 * np.pi, size=2))
    bump = tuple(rng.uniform(-0.8, 0.8, size=2))
    u_peak = peak_velocity(main)
    venc = 1.25 * u_peak
    if not surround:
        return Scene(main=main, venc=venc, surround=False, u_peak=u_peak)
    artery = StarPoiseuille(
        lumen=Circle(center=(20.0 + jitter[3], -17.0 + jitter[4]), r=4.0), viscosity_pa_s=3.5e-3, u_max=0.35
    )
    vein = StarPoiseuille(
        lumen=Circle(center=(-21.0 + jitter[5], -21.5 + 0.5 * jitter[6]), r=5.0), viscosity_pa_s=3.5e-3, u_max=-0.12
    )
    fam = OFFSET_FAMILIES[0] if family is None else family
    offset = OffsetField(fam, offset_pct / 100.0 * venc, center, a, b, p, bump) if offset_pct else None
    return Scene(
        main=main,
        neighbours=(artery, vein),
        venc=venc,
        surround=True,
        offset=offset,
        u_peak=u_peak,
        texture_k=k,
        texture_phase=kphase,
        shading=shading,
        surroundings=surroundings,
        fat_blobs=((22.0 + jitter[7], 5.0, 4.0), (-24.0, 6.0 + jitter[7], 3.5))
        + _touching_fat(main.lumen, touching_fat),
    )


def _parameters(name: str, h_mm, snr, seed: int, scene: Scene, family: str, offset_pct, touching_fat: int = 0,
                **extra) -> dict:  # fmt: skip
    """The truth's parameters of a slice (or a cine frame: ``extra``), from its scene: what was drawn and chosen."""
    offset = scene.surround and family != "none" and bool(offset_pct)
    return {
        "case": name,
        "h_mm": h_mm,
        "snr": -1.0 if snr is None else float(snr),
        "seed": seed,
        **extra,
        "venc_m_s": scene.venc,
        "offset_family": family if offset else "none",
        "offset_pct_at_vessel": float(offset_pct) if offset else 0.0,
        "touching_fat": int(touching_fat) if scene.surround else 0,
        "surroundings": asdict(scene.surroundings) if scene.surround else {},
    }


def voxel_means(scene: Scene, grid: VoxelGrid, venc: float, max_points: int = MAX_POINTS):
    """Voxel means of the complex signal, of the main vessel's velocity, and the static and flowing fractions.

    The midpoint rule with points at most :data:`SPACING_MM` apart (at most ``max_points`` per axis).
    """
    n_sub = int(np.clip(np.ceil(grid.h / SPACING_MM), 4, max_points))
    t = (np.arange(n_sub) + 0.5) / n_sub - 0.5
    ox, oy = (v.ravel() for v in np.meshgrid(t * grid.dx, t * grid.dy))
    xc, yc = grid.centers()
    ny, nx = grid.shape
    signal = np.zeros((ny, nx), complex)
    u_mean, static, flowing = np.zeros((ny, nx)), np.zeros((ny, nx)), np.zeros((ny, nx))
    for iy in range(ny):  # row by row keeps memory small
        px = xc[iy][:, None] + ox[None, :]
        py = yc[iy][:, None] + oy[None, :]
        signal[iy] = scene.signal(px, py).mean(axis=1)
        reg = scene.regions(px, py)
        ins = reg["lumen"]
        u = np.where(ins, scene.main.velocity(px, py), 0.0)
        cnt = ins.sum(axis=1)
        u_mean[iy] = np.where(cnt > 0, (u * ins).sum(axis=1) / np.maximum(cnt, 1), 0.0)
        fl = ins.copy()
        for k in range(len(scene.neighbours)):
            fl |= reg[f"neighbour{k}"]
        flowing[iy] = fl.mean(axis=1)
        if scene.surround:
            static[iy] = (reg["wall"] | reg["fat"] | reg["tissue"]).mean(axis=1)
    return signal, u_mean, static, flowing


def make_invivo(
    case: str = "laminar",
    h_mm: float = 1.0,
    snr: float | None = 25.0,
    seed: int = 0,
    surround: bool = True,
    offset_pct: float = 2.0,
    offset_family: str | None = None,
    max_points: int = MAX_POINTS,
    touching_fat: int = 0,
    surroundings: Surroundings = TEXTURED,
) -> tuple[Acquisition, InvivoTruth]:
    """Seeded in-vivo-like phantom: ``(acquisition, truth)`` of one slice in a 64 x 64 mm view.

    Parameters
    ----------
    case : "laminar" or "turbulent"
        The vessel and flow of :func:`wss_nlp.synthetic.phantoms.make_phantom` (same lumen, same flow).
    h_mm : float
        Square voxel size; the view has ``ceil(64 / h)`` voxels a side.
    snr : float or None
        Noise ``1 / snr`` per channel (the lumen's base signal is 1); None: noise-free.
    seed : int
        Draws the sub-voxel offset, the texture, shading, neighbours' and fat's positions, the offset's
        coefficients and the noise. ``offset_family`` None takes ``OFFSET_FAMILIES[seed % 3]``.
    surround : bool
        False: the same vessel alone in air (the reference), same grid, shift and noise seed.
    offset_pct : float
        The eddy-current offset at the vessel's centre in percent of the venc (0: none).
    max_points : int
        Most midpoint-rule points per voxel axis (tests use fewer: a faster, coarser voxel mean; the truth's
        fractions are the same rule's).
    touching_fat : int
        Fat deposits (radius :data:`TOUCHING_FAT_MM`) pressed against the vessel's wall at equally spaced angles
        (in tissue only): with partial volume they join the lumen in one bright region of the magnitude. They
        draw nothing from the seed: the same seed gives the same noise and the same scene otherwise.
    surroundings : Surroundings
        The tissue's look (:data:`TEXTURED`, :data:`UNIFORM`, :data:`BATH`); it draws nothing from the seed
        either.
    """
    if touching_fat < 0:
        raise InputError(f"touching_fat is a number of fat deposits (>= 0), got {touching_fat}")
    family = _family(h_mm, seed, offset_family)
    rng = np.random.default_rng(seed)
    scene = _scene(
        case, rng, h_mm, surround, 0.0 if family == "none" else offset_pct, family, touching_fat, surroundings
    )
    name = f"invivo-{case}" if surround else f"air-{case}"
    params = _parameters(name, h_mm, snr, seed, scene, family, offset_pct, touching_fat)
    return _acquire(scene, _view(h_mm), snr, rng, max_points, name, f"phantom:{name}", params)


def _family(h_mm: float, seed: int, offset_family: str | None) -> str:
    """The offset family a seed draws (or the one named), after checking the voxel size and the name."""
    if not h_mm > 0:
        raise InputError(f"voxel size must be > 0 mm, got {h_mm}")
    family = OFFSET_FAMILIES[seed % 3] if offset_family is None else offset_family
    if family not in OFFSET_FAMILIES + ("none",):
        raise InputError(f"unknown offset family {family!r}; choose from {', '.join(OFFSET_FAMILIES)}")
    return family


def _view(h_mm: float) -> VoxelGrid:
    """The square view of :data:`VIEW_MM` in voxels of ``h_mm``, centred on the origin."""
    n = int(np.ceil(VIEW_MM / h_mm))
    return VoxelGrid((n, n), (h_mm, h_mm), (-(n - 1) / 2 * h_mm, -(n - 1) / 2 * h_mm))


def _acquire(scene: Scene, grid: VoxelGrid, snr, rng, max_points: int, name: str, source: str, params: dict):
    """One slice of ``scene`` on ``grid``: its voxel means with the noise drawn next from ``rng``, as
    ``(acquisition, truth)``."""
    signal, u_mean, static, flowing = voxel_means(scene, grid, scene.venc, max_points)
    if snr is not None:
        signal = complex_noise(signal, 1.0 / snr, rng)
    acq = Acquisition(
        magnitude=np.abs(signal)[None],
        phase=np.angle(signal)[None],
        voxel_size_mm=grid.voxel_size_mm,
        origin_mm=grid.origin_mm,
        venc_m_s=scene.venc,
        viscosity_pa_s=scene.main.viscosity_pa_s,
        density_kg_m3=getattr(scene.main, "density_kg_m3", None),
        source=source,
    )
    truth = InvivoTruth(
        name=name,
        flow=scene.main,
        velocity_image=u_mean,
        parameters=params,
        scene=scene,
        grid=grid,
        static_fraction=static,
        flowing_fraction=flowing,
    )
    return acq, truth


#: The cine series' waveforms: the main vessel and the artery ``u_max (A0 + A1 cos(2 pi t / T))`` (always forward),
#: the vein ``u_max cos(2 pi t / T + VEIN_PHASE)``: pulsatile, its time-mean speed zero.
CINE_MAIN, CINE_VEIN_PHASE = (0.6, 0.4), 1.0


@dataclass
class InvivoCine:
    """A seeded in-vivo-like cine series (:func:`make_invivo_cine`): frames, their times and truths."""

    frames: list
    times_ms: np.ndarray
    period_ms: float
    truths: list


def make_invivo_cine(
    h_mm: float = 1.5,
    snr: float | None = 25.0,
    seed: int = 0,
    n_frames: int = 8,
    period_ms: float = 800.0,
    offset_pct: float = 2.0,
    offset_family: str | None = None,
    max_points: int = MAX_POINTS,
) -> InvivoCine:
    """The laminar in-vivo-like slice as a cine series: the scene of :func:`make_invivo` in every frame, the flows
    pulsing, the eddy-current offset the same in every frame (the sequence repeats), fresh noise per frame.

    The main vessel and the artery pulse forward (:data:`CINE_MAIN`), the vein back and forth with a time-mean
    speed of zero (:data:`CINE_VEIN_PHASE`): in the frames' mean it looks static, over the series it flows. Each
    frame's flow is the steady profile scaled (quasi-steady: a phantom of detection and offsets, not of the
    WSS's dynamics, which needs a Womersley flow). The venc is the peak frame's (1.25 x its peak speed);
    ``offset_pct`` is the offset at the vessel in percent of that venc. The seed draws the scene as
    :func:`make_invivo` does, then each frame's noise in turn.
    """
    if n_frames < 2:
        raise InputError(f"a cine series needs at least 2 frames, got {n_frames}")
    family = _family(h_mm, seed, offset_family)
    rng = np.random.default_rng(seed)
    base = _scene("laminar", rng, h_mm, True, 0.0 if family == "none" else offset_pct, family)
    grid = _view(h_mm)
    times = np.arange(n_frames) * period_ms / n_frames
    artery, vein = base.neighbours
    main = base.main
    assert isinstance(main, PoiseuilleEllipse)  # the laminar vessel: its profile scales with u_max
    frames, truths = [], []
    for k, t in enumerate(times):
        phase = 2 * np.pi * t / period_ms
        a = CINE_MAIN[0] + CINE_MAIN[1] * np.cos(phase)
        b = np.cos(phase + CINE_VEIN_PHASE)
        scene = replace(
            base,
            main=replace(main, u_max=a * main.u_max),
            neighbours=(replace(artery, u_max=a * artery.u_max), replace(vein, u_max=b * vein.u_max)),
        )
        params = _parameters("invivo-cine", h_mm, snr, seed, scene, family, offset_pct, frame=k, time_ms=float(t))
        acq, truth = _acquire(scene, grid, snr, rng, max_points, "invivo-cine", f"phantom:invivo-cine frame {k}",
                              params)  # fmt: skip
        frames.append(acq)
        truths.append(truth)
    return InvivoCine(frames, times, float(period_ms), truths)


#: Cases the demo and ``wss-nlp phantom`` can name: case name -> (main vessel case, description).
INVIVO_CASES = {
    "invivo": (
        "laminar",
        "the laminar vessel in tissue: wall, textured tissue, fat, air, two neighbouring vessels, "
        "a 2 % venc eddy-current offset, inflow enhancement and coil shading (64 x 64 mm)",
    ),
    "invivo-turbulent": ("turbulent", "the turbulent (Re_tau 180.9) vessel in the same in-vivo-like surroundings"),
}


def make_case(
    name: str, h_mm: float = 1.0, snr: float | None = 25.0, seed: int = REPORTED_SEEDS[0], max_points: int = MAX_POINTS
):
    """``make_invivo`` by a case name of :data:`INVIVO_CASES` (the demo's and ``wss-nlp phantom``'s entry)."""
    if name not in INVIVO_CASES:
        raise InputError(f"unknown in-vivo phantom case {name!r}; choose from {', '.join(INVIVO_CASES)}")
    acq, truth = make_invivo(INVIVO_CASES[name][0], h_mm=h_mm, snr=snr, seed=seed, max_points=max_points)
    acq = replace(acq, source=f"phantom:{name}")
    truth.name = name
    truth.parameters["case"] = name
    return acq, truth
