"""Whole-vessel reconstruction from 4D flow (wss_nlp.vessel: tube, geometry3d, velocity3d, wss3d, reconstruct,
baseline, metrics), checked against brute-force voxel integration, Taylor tests, the 2D method on the same tube,
the phantoms' exact WSS and closed forms."""

import casadi as ca
import numpy as np
import pytest
from scipy import special

from wss_nlp.errors import InputError
from wss_nlp.io.volume import VolumeAcquisition
from wss_nlp.synthetic import vessels as vs
from wss_nlp.vessel import band3d
from wss_nlp.vessel import geometry3d as g3
from wss_nlp.vessel import reconstruct as vrec
from wss_nlp.vessel import tube
from wss_nlp.vessel import velocity3d as v3
from wss_nlp.vessel import wss3d
from wss_nlp.vessel.baseline import baseline_vessel, wall_normal_fit
from wss_nlp.vessel.centerline import Centerline
from wss_nlp.vessel.metrics import accuracy

MU = vs.BLOOD_VISCOSITY


def _true_centerline(vessel, lo=-30.0, hi=230.0) -> Centerline:
    """The phantom's closed-form centreline as a Centerline (``s`` shifted by ``-lo``)."""
    return Centerline.from_points(vessel.centreline.point(np.linspace(lo, hi, 1500)))


def _taylor_orders(fun, x, d, derivative, epsilons=(1e-2, 5e-3, 2.5e-3)):
    """Observed orders of the first-order Taylor remainder ``|f(x + e d) - f(x) - e f'(x) d|`` as e halves."""
    f0 = fun(x)
    rem = [np.linalg.norm(np.ravel(fun(x + e * d) - f0 - e * derivative)) for e in epsilons]
    return [np.log2(rem[i] / rem[i + 1]) for i in range(len(rem) - 1)], rem


# ------------------------------------------------------------------ B-splines and the wall basis
def test_splines_sum_to_one_and_their_derivatives_pass_a_taylor_test():
    sp = tube.SplineBasis(3.0, 41.0, 2.0)
    s = np.random.default_rng(0).uniform(3.0, 41.0, 200)
    assert np.allclose(sp.matrix(s).sum(axis=1), 1.0, atol=1e-14)  # partition of unity, to rounding
    c = np.random.default_rng(1).normal(size=sp.size)
    for nu in (0, 1):  # B and B' have Lipschitz derivatives (cubic splines are C^2); the third derivative jumps
        orders, _ = _taylor_orders(lambda x: sp.evaluate(c, x, nu), s, np.ones_like(s), sp.evaluate(c, s, nu + 1))
        assert min(orders) > 1.8  # second-order remainder: the derivative is exact
    # the Gram matrix of second derivatives integrates a known spline exactly: f = s^2 -> int f''^2 = 4 (b - a)
    coef = sp.fit(np.linspace(3, 41, 400), np.linspace(3, 41, 400) ** 2)
    assert coef @ sp.gram(2) @ coef == pytest.approx(4 * 38.0, rel=1e-9)


def test_wall_design_matrix_and_evaluation_agree():
    basis = tube.WallBasis(tube.SplineBasis(0.0, 30.0, 2.5), 4)
    rng = np.random.default_rng(2)
    c = rng.normal(size=basis.size)
    s, phi = rng.uniform(0, 30, 300), rng.uniform(-np.pi, np.pi, 300)
    for ds, dphi in ((0, 0), (1, 0), (0, 1)):
        assert np.allclose(basis.design(s, phi, ds, dphi) @ c, basis.evaluate(c, s, phi, ds, dphi), atol=1e-12)


# ------------------------------------------------------------------ the forward model
@pytest.fixture(scope="module")
def arc_noise_free():
    """The arch at h = 2 mm without noise over a 35 mm stretch (fast) and its truth."""
    vol, truth = vs.make_vessel_phantom("arc", h_mm=2.0, snr=None, seed=3, visible_mm=(50.0, 85.0))
    return vol, truth


def test_forward_model_matches_brute_force_voxel_integration(arc_noise_free):
    vol, truth = arc_noise_free
    cl = _true_centerline(truth.vessel)
    frame = tube.FrameTable(cl)
    idx = np.argwhere(np.ones(vol.shape, bool))
    co = tube.voxel_coordinates(vol, idx, cl)
    rng = np.random.default_rng(4)
    near = np.flatnonzero((np.abs(co.r - 11.0) < 2.0) & (co.s > 80.0) & (co.s < 120.0))
    pick = rng.choice(near, 80, replace=False)
    sub = tube.VoxelCoordinates(co.index[pick], co.world[pick], co.s[pick], co.r[pick], co.phi[pick], co.beyond[pick])
    basis = tube.WallBasis(tube.SplineBasis(60.0, 140.0, 2.0), 3)
    c = basis.constant(np.full(basis.spline.size, 11.0))  # the phantom's circle of radius 11 mm, exactly

    def band(s, phi):
        return np.full(np.shape(s), 11.0)

    # brute force: the sharp indicator (the phantom's closed form) at 16^3 points per voxel, its own code (its
    # midpoint error, ~1e-3, is a quarter of the model's at q = 8)
    fine = tube.subvoxel_offsets(16)
    a = np.asarray(vol.affine_mm, float)
    pts = (sub.index[:, None, :] + fine[None]).reshape(-1, 3) @ a[:3, :3].T + a[:3, 3]
    exact = truth.vessel.inside(truth.vessel.local(pts, frame=False)).reshape(len(pick), -1).mean(axis=1)
    errors = {}
    for q in (4, 8):
        model = tube.build_model(vol, sub, frame, basis, q, 2.0 / q, band, band)
        order = [int(np.flatnonzero((sub.index == v).all(axis=1))[0]) for v in model.voxel_index]
        errors[q] = np.sqrt(np.mean((model.predict(c) - exact[order]) ** 2))
        # the same model as matrices: F = constant + S H_gamma(A c - r)
        alt = model.constant + model.averaging @ (0.5 * (1 + special.erf((model.design_matrix() @ c - model.r) /
                                                                          model.gamma)))  # fmt: skip
        assert np.allclose(alt, model.predict(c), atol=1e-13)
        # and through CasADi's graph
        sym = tube.symbolic(model)
        assert np.allclose(np.asarray(ca.Function("F", [sym.c], [sym.predicted])(c)).ravel(), model.predict(c),
                           atol=1e-13)  # fmt: skip
    # the model converges to the voxel means as the points refine (gamma = h / q shrinks with them): the error of
    # the smoothed midpoint rule falls roughly like 1/q; at q = 8 (gamma = 0.25 mm) it is a few 1e-3 (measured
    # 4e-3 RMS on 6000 wall voxels of this arch), below a tenth of the noise at SNR 20
    assert errors[8] < 0.6 * errors[4]
    assert errors[8] < 6e-3


def test_fast_coordinates_agree_with_the_centerline_projection():
    helix = vs.build_centreline((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (1.0, 0.0, 0.0), [vs.HelixSegment(8.0, 14.0, 100.0)])
    cl = Centerline.from_points(helix.point(np.linspace(-20.0, 120.0, 800)))
    frame = tube.FrameTable(cl)
    rng = np.random.default_rng(5)
    x = cl.position(rng.uniform(30.0, 100.0, 500)) + rng.normal(size=(500, 3)) * 5.0
    exact = cl.project(x)
    s, r, phi = frame.project(x, exact.s + rng.uniform(-1.0, 1.0, 500))  # starts a voxel's half-width away
    # the Hermite resampling (0.25 mm) of a smooth curve: its interpolation error, far below the voxels' 2.5 mm
    assert np.max(np.abs(s - exact.s)) < 1e-5
    assert np.max(np.abs(r - exact.r)) < 1e-5
    assert np.max(np.abs(np.angle(np.exp(1j * (phi - exact.phi))))) < 1e-5


# ------------------------------------------------------------------ derivatives
@pytest.fixture(scope="module")
def small_problem():
    """A short straight tube with noise (non-zero residuals) as a geometry problem."""
    vol, truth = vs.make_vessel_phantom("straight", h_mm=2.5, snr=20, seed=2, visible_mm=(20.0, 32.0),
                                        radius_mm=7.0)  # fmt: skip
    inputs = vrec.vessel_inputs(vol)
    cl = inputs.centerline
    import scipy.ndimage as ndi

    co = tube.voxel_coordinates(vol, np.argwhere(ndi.binary_dilation(inputs.mask, iterations=5)), cl)
    vis = inputs.record["visible"]
    problem = g3.problem_from_mask(vol, cl, inputs.mask, co, (vis[0][0], vis[-1][1]), np.linspace(0, cl.length_mm, 60))
    return vol, truth, problem


def test_geometry_gradient_newton_hessian_and_jacobian_are_exact(small_problem):
    vol, _, problem = small_problem
    opts = g3.Geometry3DOptions(n_fourier=3)
    basis = tube.WallBasis(tube.SplineBasis(*problem.s_range, 2.5), 3)
    r0 = float(np.mean(problem.radius_estimate(np.linspace(*problem.s_range, 20))))
    f, r, nlp = g3.functional(
        problem,
        basis,
        opts,
        2,
        lambda s, p: np.full(np.shape(s), r0 - 2.0),
        lambda s, p: np.full(np.shape(s), r0 + 2.0),
        basis.constant(np.full(basis.spline.size, r0)),
    )
    rng = np.random.default_rng(6)
    c = basis.constant(np.full(basis.spline.size, r0)) + 0.05 * rng.normal(size=basis.size)
    d = rng.normal(size=basis.size)
    value, grad = (np.asarray(v).ravel() for v in f(c))
    orders, _ = _taylor_orders(lambda x: float(f(x)[0]), c, d, float(grad @ d))
    assert min(orders) > 1.8  # CasADi's gradient through the callbacks' exact adjoints
    res, jac = r(c)
    jac = np.asarray(ca.densify(jac))
    orders, _ = _taylor_orders(lambda x: np.asarray(r(x)[0]).ravel(), c, d, jac @ d)
    assert min(orders) > 1.8  # the chain-rule Jacobian S diag(H') A
    # the Newton Hessian by the chain rule (J^T J, A^T diag(d) A and the penalties) equals CasADi's own Hessian of
    # the objective: two exact computations of one matrix, equal to rounding
    mine = np.asarray(ca.densify(ca.Function("H", [nlp.c], [nlp.hessian])(c)))
    exact = np.asarray(ca.Function("h", [nlp.c], [ca.hessian(nlp.f, nlp.c)[0]])(c))
    assert np.max(np.abs(mine - exact)) <= 1e-8 * np.max(np.abs(exact))


@pytest.fixture(scope="module")
def small_wall(small_problem):
    # no outside-level updates: the tests on this wall check derivatives and bookkeeping, not its accuracy
    return g3.fit_wall(small_problem[2], g3.Geometry3DOptions(n_fourier=3, outside_updates=0))


def test_wss_derivative_graph_passes_a_taylor_test(small_problem, small_wall):
    vol, _, problem = small_problem
    geo = small_wall
    vopt = v3.Velocity3DOptions(beta=1e-4)
    vp = v3.assemble(vol, geo, problem.frame, problem.coords, vopt)
    vel = v3.fit_velocity(vol, vp, vopt)
    cl = problem.centerline
    rng = np.random.default_rng(7)
    s = rng.uniform(*geo.s_range, 6)
    s = np.clip(s, geo.s_range[0] + 5, geo.s_range[1] - 5)
    theta, rho = rng.uniform(-np.pi, np.pi, 6), rng.uniform(0.3, 0.8, 6)
    ev = wss3d.evaluate(cl, geo, vel, s, theta, rho=rho, mu=MU)
    basis = vel.basis

    def u_at(x):  # the velocity at world points through the exact projection: independent of the CasADi graph
        p = cl.project(np.atleast_2d(x))
        return basis.evaluate(vel.coefficients[0], p.s, p.r, p.phi)[0]

    for i in range(6):
        d = rng.normal(size=3)
        orders, rem = _taylor_orders(u_at, ev.x[i], d, ev.grad[0, i] @ d / wss3d.PER_MM)
        assert min(orders) > 1.7, (orders, rem)


# ------------------------------------------------------------------ against the 2D method
def test_noise_free_straight_tube_equals_the_2d_result():
    """A z-invariant volume made of one 2D phantom slice: the 3D functionals are the 2D ones summed over the voxel
    layers (same points in each layer, z-invariant wall and velocity, s-penalties zero), so with the same options
    (N, alpha, q, basis, beta, r_in = min R as in 2D) the 3D wall and WSS equal the 2D method's (models.geometry,
    models.velocity, models.wss) to the solvers' tolerances: measured 2e-10 (radius) and 4e-5 (axial WSS)
    relative."""
    from wss_nlp.models import geometry as geo
    from wss_nlp.models import preprocess as pp
    from wss_nlp.models import velocity as vel
    from wss_nlp.models import wss as wss2d
    from wss_nlp.synthetic import phantoms

    acq, _ = phantoms.make_phantom("circle", h_mm=2.0, snr=None, seed=3, venc=100.0)
    grid = acq.grid
    m2d = pp.normalize_magnitude(acq.magnitude[0], pp.histogram_peaks(acq.magnitude[0]))
    lum = pp.find_lumen(m2d, grid)
    u2d = acq.velocity_images()[0]
    n, q = 6, 4
    g2 = geo.solve_ipopt(geo.GeometryProblem(grid, m2d, lum.center, lum.r0, lum.r1, lum.r_area),
                         geo.GeometryOptions(n_fourier=n, alpha=1e-6, quad_order=q))  # fmt: skip
    vopt = vel.VelocityOptions(degree=10, angular_order=4, beta=1e-6, laplacian_power=2, inner_fraction=1.0,
                               quad_order=3, near_wall="off")  # fmt: skip
    v2 = vel.solve(vel.assemble(grid, u2d, g2.coefficients, lum.center, vopt), vopt)
    w2 = wss2d.from_reconstruction(v2, 720, MU)
    nk, dz = 12, grid.dx
    ny, nx = m2d.shape
    aff = np.diag([grid.dx, grid.dy, dz, 1.0])
    aff[:3, 3] = (grid.origin_mm[0], grid.origin_mm[1], 0.0)
    vel3 = np.zeros((1, 3, nx, ny, nk))
    vel3[0, 2] = np.repeat(u2d.T[:, :, None], nk, axis=2)
    vol = VolumeAcquisition(np.repeat(m2d.T[:, :, None], nk, axis=2)[None], vel3, aff, viscosity_pa_s=MU)
    cx, cy = lum.center
    cl = Centerline.from_points(np.array([[cx, cy, -10.0], [cx, cy, (nk - 1) * dz + 10.0]]))
    record = {"visible": [[10.0 + 1.5 * dz, 10.0 + (nk - 2.5) * dz]], "branches": []}  # whole voxel layers 2..9
    opts = vrec.VesselOptions(
        geometry=g3.Geometry3DOptions(n_fourier=n, alpha=1e-6, quad_order=q, outside_updates=0),
        velocity=v3.Velocity3DOptions(degree=10, angular_order=4, beta=1e-6, inner="min", quad_order=3),
        extend_mm=0.0, s_spacing_mm=dz, n_phi=32,
    )  # fmt: skip
    res = vrec.reconstruct_vessel(vol, opts, m2d.T[:, :, None].repeat(nk, 2) > 0.5, cl, record)
    phi2 = np.arctan2(res.wall_mm[..., 1] - cy, res.wall_mm[..., 0] - cx)  # the 2D angles of the 3D wall points
    r2 = g2.radius(phi2.ravel()).reshape(phi2.shape)
    assert np.max(np.abs(res.radius_mm - r2)) <= 1e-3 * float(np.mean(r2))
    tau2 = np.interp(np.mod(phi2, 2 * np.pi).ravel(), w2.phi, w2.tau, period=2 * np.pi).reshape(phi2.shape)
    assert np.max(np.abs(res.axial_pa[0] - tau2)) <= 1e-3 * float(np.mean(tau2))
    assert np.max(np.abs(res.circumferential_pa)) <= 1e-6 * float(np.mean(tau2))  # only u_z: no swirl


# ------------------------------------------------------------------ phantoms
@pytest.fixture(scope="module")
def arc_result(arc_noise_free):
    """The reconstruction and the baseline of the noise-free arch stretch, with a made-up side branch flagged."""
    vol, truth = arc_noise_free
    inputs = vrec.vessel_inputs(vol)
    record = dict(inputs.record)
    mid = 0.5 * (record["visible"][0][0] + record["visible"][-1][1])
    record["branches"] = [{"s_mm": mid, "phi": 1.0, "flag": {"s_mm": [mid - 3.0, mid + 3.0], "phi": [0.6, 1.4]}}]
    res = vrec.reconstruct_vessel(vol, None, inputs.mask, inputs.centerline, record)
    base = baseline_vessel(vol, inputs.mask, inputs.centerline, record, s=res.s_mm, phi=res.phi)
    return vol, truth, res, base


def test_curved_phantom_noise_free_wss(arc_result):
    vol, truth, res, _ = arc_result
    acc = accuracy(res, truth)
    # noise-free (beta: velocity3d.NOISE_FREE_BETA), the error comes from the centreline extracted from the mask
    # (0.15 mm RMS off the true one) and the voxel model: 0.8 % measured on this stretch, 0.7 % on the whole arch at
    # h = 2 mm (0.4 % with the true centreline); 2 % leaves room for other grids
    assert acc.wss_rel_l2 < 0.02
    assert acc.axial_rel_l2 < 0.02
    assert acc.wall_rms_mm < 0.05 * 2.0  # far inside h / 4 (measured 0.01 mm)
    assert acc.coverage > 0.9


def test_branch_regions_are_flagged_not_fitted(arc_result):
    _, _, res, base = arc_result
    b = res.record["branches"][0]["flag"]
    ss, pp = np.meshgrid(res.s_mm, res.phi, indexing="ij")
    inside = (ss >= b["s_mm"][0]) & (ss <= b["s_mm"][1]) & (np.abs(np.angle(np.exp(1j * (pp - 1.0)))) <= 0.4)
    assert inside.any()
    assert np.all(res.flags[inside] & vrec.FLAG_BRANCH)
    assert not np.any(res.flags[~inside] & vrec.FLAG_BRANCH)
    assert np.array_equal(base.flags & vrec.FLAG_BRANCH, res.flags & vrec.FLAG_BRANCH)


def test_the_baseline_runs_on_the_same_mask_and_grid(arc_result):
    vol, truth, res, base = arc_result
    assert base.method == "wall-normal fit" and base.wss_pa.shape == res.wss_pa.shape
    assert np.array_equal(base.s_mm, res.s_mm) and np.array_equal(base.phi, res.phi)
    acc = accuracy(base, truth)
    # on this noise-free arch the mask's surface lies 0.3 mm inside the wall and the fit over 1-4 mm overestimates:
    # the baseline's error is several times ours (measured 25 % against 1.4 % on the whole arch)
    assert acc.wss_rel_l2 > 2 * accuracy(res, truth).wss_rel_l2
    assert 0.5 < acc.mean_wss_pa / acc.true_mean_wss_pa < 2.0


def test_the_wall_normal_fit_takes_the_slope_of_the_profile_at_its_surface():
    """A straight tube sampled at voxel centres (no partial volume), 1 mm voxels, radius 15 mm, Poiseuille flow.
    The fit forces ``u = 0`` at the mask's surface ``r_w`` (within half a voxel of the wall) and fits
    ``a d + b d^2`` to the samples ``u(r_w - d_k)``: its slope is that of the least-squares fit of the exact profile
    ``U (1 - (r_w - d)^2 / R^2)`` on the same ``d_k``, to the trilinear interpolation's error (the first sample
    interpolates towards the zero velocity of the voxels outside the mask: measured up to 2.6 % of the slope,
    4 % allowed); its surface is within half a voxel of the wall and its normal along the radius."""
    n, h, radius, u_peak = 41, 1.0, 15.0, 0.5
    idx = np.stack(np.meshgrid(np.arange(n), np.arange(n), np.arange(10), indexing="ij"), -1).astype(float)
    aff = np.diag([h, h, h, 1.0])
    aff[:3, 3] = (-(n - 1) / 2 * h, -(n - 1) / 2 * h, 0.0)
    world = idx @ aff[:3, :3].T + aff[:3, 3]
    r2 = world[..., 0] ** 2 + world[..., 1] ** 2
    mask = r2 < radius**2
    vel = np.zeros((1, 3, n, n, 10))
    vel[0, 2] = np.where(mask, u_peak * (1 - r2 / radius**2), 0.0)
    vol = VolumeAcquisition(mask[None].astype(float), vel, aff, viscosity_pa_s=MU)
    cl = Centerline.from_points(np.array([[0.0, 0.0, -5.0], [0.0, 0.0, 15.0]]))
    s, phi = np.array([10.0, 12.0]), np.linspace(0, 2 * np.pi, 16, endpoint=False)
    fit = wall_normal_fit(vol, mask, cl, {"radius": {"radius_mm": [radius]}}, s, phi, MU)
    assert np.all(fit["found"]) and np.max(np.abs(fit["radius"] - radius)) < 0.51 * h  # 0.5 along the axes
    radial = fit["wall"][..., :2] / np.linalg.norm(fit["wall"][..., :2], axis=-1, keepdims=True)
    # the staircase of a voxelized circle, smoothed by one voxel: within 3 degrees of the radius
    assert np.max(np.abs(fit["normal"][..., :2] - radial)) < 0.05 and np.max(np.abs(fit["normal"][..., 2])) < 1e-9
    d = np.array([0.5, 1.0, 1.5, 2.0]) * h
    design = np.stack([d, d**2], axis=1)
    r_w = fit["radius"][..., None]
    profile = u_peak * (1 - (r_w - d) ** 2 / radius**2)  # the exact field at the samples
    slope = np.einsum("k,ijk->ij", np.linalg.pinv(design)[0], profile)
    tau = fit["tau"][0]
    assert np.allclose(tau[..., 2], MU * slope * 1e3, rtol=0.04)
    assert np.max(np.abs(tau[..., :2])) < 1e-9  # tangential: along the axis


def test_an_oblique_small_tube_gives_the_axis_aligned_wss():
    """The fast version of the claim below: a radius-6 mm tube at h = 2.5 mm (2.4 voxels per radius), 20 mm in
    view, SNR 20, seed 4, on a grid along its axis and on one turned at random. The ring-mean WSS of both equal
    ``2 mu U / R`` within 3 %: measured 1.6 % and 0.3 % off (seeds 6 and 7: up to 1.1 % and 1.0 %, the two
    grids 1-2 % apart); the WSS vector's L2 error 11.5 % and 12.8 % (the issue's h = 2.5 mm target is 12 % for
    aorta-sized vessels, twice this radius), bound at 15 %."""
    means = []
    for rotation in (np.eye(3), None):
        vol, truth = vs.make_vessel_phantom("straight", h_mm=2.5, snr=20, seed=4, visible_mm=(20.0, 40.0),
                                            radius_mm=6.0, rotation=rotation)  # fmt: skip
        acc = accuracy(vrec.reconstruct_vessel(vol), truth)
        means.append(acc.mean_wss_pa)
        assert acc.wss_rel_l2 < 0.15
    expected = 2 * MU * 0.8 / 6e-3
    assert abs(means[0] - means[1]) < 0.03 * expected
    assert max(abs(m - expected) for m in means) < 0.03 * expected


def test_a_grid_aligned_tube_two_voxels_across_survives_the_segmentation():
    """The radius-6 mm tube at h = 2.5 mm on a grid along its axis, noise-free, seed 5 (its sub-voxel offset): its
    PC-MRA core is two voxels across, which the 6-neighbour opening erased whole (NoVesselError before the fix).
    The segmentation now keeps the thresholded voxels when nothing survives the opening, and says so; the ring-mean
    WSS is ``2 mu U / R`` within 3 % (measured 0.2 %; SNR 20: 0.6 %), the WSS vector's L2 error within the 15 %
    of the test above (measured 8.2 %)."""
    from wss_nlp.vessel import segmentation

    vol, truth = vs.make_vessel_phantom("straight", h_mm=2.5, snr=None, seed=5, visible_mm=(20.0, 40.0),
                                        radius_mm=6.0, rotation=np.eye(3))  # fmt: skip
    seg = segmentation.segment_vessel(vol)
    assert seg.record["opening_iterations"] == 0 and "opening_skipped" in seg.record
    res = vrec.reconstruct_vessel(vol)
    acc = accuracy(res, truth)
    expected = 2 * MU * 0.8 / 6e-3
    assert abs(acc.mean_wss_pa - expected) < 0.03 * expected
    assert acc.wss_rel_l2 < 0.15
    # the plane table in its units: Poiseuille flow Q = pi R^2 U / 2 = 45.24 mL/s (mm^2 m/s = mL/s; it was 1000x
    # small) and the bulk Reynolds number rho (U/2) 2R / mu = 1454 with blood's density, within 2 % (the
    # reconstructed area and velocity: measured 0.3 % and 0.6 % off on this tube); below 2300: no note
    keep = res.planes["flags"] == 0
    q_true = np.pi * 6.0**2 * 0.8 / 2
    assert np.allclose(res.planes["flow_ml_s"][:, keep], q_true, rtol=0.02)
    re = vrec.bulk_reynolds(res.planes, MU, 1060.0)[:, keep]
    assert np.allclose(re, 1060.0 * 0.4 * 12e-3 / MU, rtol=0.02)
    assert vrec.reynolds_note(res.planes, MU, None, res.time_ms) is None
    assert not any("Reynolds" in n for n in res.notes)
    # noise-free data get the fixed beta, and the result says so (it over-smooths blunt profiles)
    assert res.parameters["beta"] == v3.NOISE_FREE_BETA
    assert any(n.startswith("noise-free data: beta fixed at 1e-05") for n in res.notes)
    # twice the flow: Re 2908 > 2300, the note names the number and the stated density
    fast = dict(res.planes, flow_ml_s=2 * res.planes["flow_ml_s"])
    note = vrec.reynolds_note(fast, MU, 1060.0, res.time_ms)
    assert note is not None and f"{np.median(2 * re):.0f}" in note and "stated" in note


@pytest.mark.slow
def test_an_oblique_straight_tube_gives_the_axis_aligned_wss():
    """The same straight tube (radius 8 mm, 2 mm voxels, 40 mm in view) on a grid along its axis and on one turned
    at random: the ring-mean axial WSS of both equal the truth's ``2 mu U / R`` within the noise (SNR 20: measured
    spread of the reconstruction's mean WSS over development seeds 0-4 about 1 %), so they agree within 3 %."""
    means = []
    for rotation in (np.eye(3), None):
        vol, truth = vs.make_vessel_phantom("straight", h_mm=2.0, snr=20, seed=4, visible_mm=(20.0, 60.0),
                                            radius_mm=8.0, rotation=rotation)  # fmt: skip
        res = vrec.reconstruct_vessel(vol)
        acc = accuracy(res, truth)
        means.append(acc.mean_wss_pa)
        assert acc.wss_rel_l2 < 0.1
    expected = 2 * MU * 0.8 / 8e-3
    assert abs(means[0] - means[1]) < 0.03 * expected
    assert abs(means[1] - expected) < 0.03 * expected


# ------------------------------------------------------------------ cycles, files, refusals
def test_tawss_and_osi_of_steady_and_oscillating_vectors():
    times = np.arange(16) * 1000.0 / 16
    e = np.array([0.3, -0.4, 0.0])  # |e| = 0.5 Pa
    steady = np.broadcast_to(e, (16, 2, 3))
    tawss, osi = vrec.cycle_indices(steady, times, 1000.0)
    assert np.allclose(tawss, 0.5) and np.allclose(osi, 0.0)
    wave = np.cos(2 * np.pi * times / 1000.0)[:, None, None] * e  # reverses: mean zero, |cos| mean 2 / pi
    tawss, osi = vrec.cycle_indices(wave, times, 1000.0)
    # the periodic trapezoid (equal weights here) of |cos| on 16 points: its mean, to rounding (2 / pi to 1.3 %);
    # the net vector is zero to rounding, so OSI = 1/2
    assert np.allclose(tawss, 0.5 * np.mean(np.abs(np.cos(2 * np.pi * times / 1000.0))), rtol=1e-12)
    assert np.allclose(osi, 0.5, atol=1e-12)


def test_the_result_round_trips_through_hdf5(arc_result, tmp_path):
    _, _, res, base = arc_result
    path = tmp_path / "result.h5"
    vrec.write_result(path, res, mode="w")
    vrec.write_result(path, base)
    back, back_base = vrec.read_result(path), vrec.read_result(path, "baseline")
    for a, b in ((res, back), (base, back_base)):
        assert b.method == a.method
        for name in ("s_mm", "phi", "wall_mm", "normal", "radius_mm", "area_mm2", "flags", "wss_pa", "axial_pa"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert np.array_equal(a.centerline.samples[1], b.centerline.samples[1])
        assert b.plane_table() == a.plane_table()
    assert back.parameters["beta"] == res.parameters["beta"]
    with pytest.raises(InputError, match="no 'vessel' group"):
        vrec.read_result(_empty_h5(tmp_path))


def _empty_h5(tmp_path):
    import h5py

    path = tmp_path / "empty.h5"
    with h5py.File(path, "w"):
        pass
    return path


def _tube_volume(**changes) -> VolumeAcquisition:
    vol, _ = vs.make_vessel_phantom("straight", h_mm=2.5, snr=20, seed=1, visible_mm=(20.0, 40.0), radius_mm=6.0)
    for k, v in changes.items():
        setattr(vol, k, v)
    return vol


@pytest.mark.parametrize(
    "change, match",
    [
        ("same", "velocity components x and y are identical"),
        ("still", "the velocity is zero everywhere"),
        ("viscosity", "no viscosity"),
    ],
)
def test_refusals_are_one_input_error_line(change, match):
    vol = _tube_volume()
    if change == "same":
        vol.velocity[:, 1] = vol.velocity[:, 0]
    elif change == "still":
        vol.velocity[:] = 0.0
    else:
        vol.viscosity_pa_s = None
    with pytest.raises(InputError, match=match) as info:
        vrec.reconstruct_vessel(vol)
    assert "\n" not in str(info.value)


def test_the_discrepancy_rule_needs_the_venc(small_problem, small_wall):
    vol, _, problem = small_problem
    geo = small_wall
    vopt = v3.Velocity3DOptions(beta="discrepancy")
    vp = v3.assemble(vol, geo, problem.frame, problem.coords, vopt)
    chosen = v3.fit_velocity(vol, vp, vopt, levels=problem.levels)
    assert chosen.beta_choice.rule == "discrepancy" and chosen.beta > 0
    blind = VolumeAcquisition(vol.magnitude, vol.velocity, vol.affine_mm, None, vol.viscosity_pa_s, source="blind.h5")
    with pytest.raises(InputError, match="blind.h5: .*venc") as info:
        v3.fit_velocity(blind, vp, vopt, levels=problem.levels)
    assert "\n" not in str(info.value)


# ------------------------------------------------------------------ slow studies
@pytest.mark.slow
def test_the_arch_at_snr_20_within_the_issue_target():
    vol, truth = vs.make_vessel_phantom("swirl", h_mm=2.0, snr=20, seed=5)
    acc = accuracy(vrec.reconstruct_vessel(vol), truth)
    assert acc.wss_rel_l2 < 0.08 and acc.wall_rms_mm < 0.5 and acc.coverage > 0.9


@pytest.mark.slow
def test_the_pulsatile_arch_tawss_and_osi():
    vol, truth = vs.make_vessel_phantom("pulsatile", h_mm=2.0, snr=20, seed=5, frames=20)
    acc = accuracy(vrec.reconstruct_vessel(vol), truth)
    assert acc.tawss_rel_l2 < 0.1 and acc.osi_rms < 0.05


def test_the_wall_mesh_opens_with_meshio_in_world_coordinates(arc_result, tmp_path):
    meshio = pytest.importorskip("meshio")
    from wss_nlp.vessel.mesh import write_wall

    _, _, res, _ = arc_result
    files = write_wall(res, tmp_path / "wall.vtu")
    mesh = meshio.read(files[0])
    assert np.allclose(mesh.points, res.wall_mm.reshape(-1, 3))  # world mm, the volume's frame
    assert mesh.cells[0].type == "quad" and mesh.cells[0].data.shape == ((res.s_mm.size - 1) * res.phi.size, 4)
    assert np.allclose(mesh.point_data["wss_vector_pa"], res.wss_pa[0].reshape(-1, 3))
    assert np.allclose(mesh.point_data["tau_pa"], res.axial_pa[0].ravel())
    assert Centerline.from_file(files[1]).length_mm == pytest.approx(res.centerline.length_mm, rel=1e-3)
    with open(files[2]) as fh:  # closed: an unclosed file is a ResourceWarning
        assert fh.readline().startswith("s_mm,area_mm2,flow_ml_s")


def test_the_wall_pieces_give_the_point_graph_wss(small_problem, small_wall):
    """:func:`wss3d.wall_wss` (the velocity-independent pieces from CasADi, the linear part in NumPy) equals the
    whole graph of :func:`wss3d.point_function` (one CasADi expression) to rounding."""
    vol, _, problem = small_problem
    vopt = v3.Velocity3DOptions(beta=1e-4)
    vel = v3.fit_velocity(vol, v3.assemble(vol, small_wall, problem.frame, problem.coords, vopt), vopt)
    s, phi = wss3d.wall_grid(small_wall.s_range, 2.5, 16)
    ss, pp = (v.ravel() for v in np.meshgrid(s, phi, indexing="ij"))
    fast = wss3d.wall_wss(problem.centerline, small_wall, vel, ss, pp, mu=MU)
    full = wss3d.evaluate(problem.centerline, small_wall, vel, ss, pp, mu=MU)
    scale = np.max(np.abs(full.tau))
    assert np.max(np.abs(fast.tau - full.tau)) <= 1e-12 * scale
    assert np.max(np.abs(fast.axial - full.axial)) <= 1e-12 * scale
    assert np.allclose(fast.x, full.x, atol=1e-12) and np.allclose(fast.normal, full.normal, atol=1e-14)


# ------------------------------------------------------------------ the velocity map on a wall far from round
def _stand_in_wall(squash: float):
    """A fitted wall stand-in (what :func:`velocity3d.velocity_basis` reads): round, radius 3 mm, on s in [0, 40] mm,
    its first 6 mm an ellipse of semi-axes ``3 + squash`` and ``3 - squash`` (mean radius about 3 mm, the smallest
    ``3 - squash``), as the loose end of a carotid's fit was (the reported carotid row, h = 2 mm, crashed on it)."""
    from types import SimpleNamespace

    basis = tube.WallBasis(tube.SplineBasis(0.0, 40.0, 2.0), 2)
    s = np.linspace(0.0, 40.0, 161)
    phi = np.linspace(-np.pi, np.pi, 48, endpoint=False)
    ss, pp = np.meshgrid(s, phi, indexing="ij")
    e = squash * (ss < 6.0)
    a, b = 3.0 + e, 3.0 - e
    radius = a * b / np.sqrt((b * np.cos(pp)) ** 2 + (a * np.sin(pp)) ** 2)
    c = basis.fit(ss.ravel(), pp.ravel(), radius.ravel())
    wall = SimpleNamespace(basis=basis, coefficients=c, s_range=(0.0, 40.0),
                           radius=lambda s_, p_: basis.evaluate(c, s_, p_))  # fmt: skip
    return wall, basis


def test_a_wall_far_from_round_caps_the_maps_inner_radius_there_only():
    opts = v3.Velocity3DOptions()
    s = np.linspace(0.0, 40.0, 801)
    phi = np.linspace(0.0, 2 * np.pi, 64, endpoint=False)
    ss, pp = np.meshgrid(s, phi, indexing="ij")
    # semi-axes 4.6 x 1.4 mm: the mean radius ~3.3 mm is more than twice the smallest, which the plain "mean"
    # rule's map cannot take (before the cap: an InputError ending the whole vessel)
    wall, basis = _stand_in_wall(1.6)
    vb = v3.velocity_basis(wall, opts, h=2.0)
    assert vb.capped and max(b for _, b in vb.capped) <= 6.0 + 8.0  # only B-splines reaching the squashed end
    r_min = wall.radius(ss.ravel(), pp.ravel()).reshape(ss.shape).min(axis=1)
    # what the map needs (one-to-one: r_in < 2 min R), and the cap's bound (a convex combination of capped
    # coefficients), which holds on the cap's samples h/8 = 0.25 mm apart: between them this wall's radius
    # (|R_ss| < 1.5 /mm on the squashed end) dips by at most 0.25^2 * 1.5 / 8 < 0.012 mm
    assert np.all(vb.r_in(s) < 2 * r_min)
    assert np.all(vb.r_in(s) <= v3.MAX_INNER_RATIO * (r_min + 0.012))
    free = s > max(b for _, b in vb.capped)
    plain = basis.spline.evaluate(basis.matrix(wall.coefficients)[:, 0], s)
    assert np.array_equal(vb.r_in(s)[free], plain[free])  # elsewhere the "mean" rule's own inner radius
    # the map is one-to-one and reaches the wall: rho = 1 at the wall on the capped part too
    rho, _ = vb.reference(ss.ravel(), wall.radius(ss.ravel(), pp.ravel()), pp.ravel())
    assert np.allclose(rho, 1.0, atol=1e-9)
    # a round wall: nothing capped, the plain rule's coefficients exactly
    round_wall, round_basis = _stand_in_wall(0.0)
    vb0 = v3.velocity_basis(round_wall, opts, h=2.0)
    assert vb0.capped == []
    assert np.array_equal(vb0.inner, round_basis.matrix(round_wall.coefficients)[:, 0])


def _flags_of(radius, capped):
    """:func:`reconstruct._flags` of a wall of these radii on s = 0..40 mm (1 mm apart) at h = 2 mm, well inside the
    field of view, with converged solvers, no active box row, the velocity map's inner radius capped on ``capped``."""
    from types import SimpleNamespace

    s = np.linspace(0.0, 40.0, 41)
    phi = np.linspace(-np.pi, np.pi, 16, endpoint=False)
    wall = np.stack(np.meshgrid(s, phi, indexing="ij"), axis=-1)
    wall = np.concatenate([np.full(wall.shape[:2] + (2,), 50.0), wall[..., :1]], axis=-1)  # x = y = 50, z = s
    geometry = SimpleNamespace(box_active=np.zeros((0, 0), bool), stats=[SimpleNamespace(converged=True)])
    velocity = SimpleNamespace(basis=SimpleNamespace(capped=capped))
    affine = np.eye(4)
    affine[2, 3] = -20.0  # 1 mm voxels, the wall (z = s in [0, 40]) 20 mm or more inside every face
    vol = SimpleNamespace(affine_mm=affine, shape=(100, 100, 100))
    flags = vrec._flags(s, phi, wall, radius, geometry, velocity, {"visible": [(0.0, 40.0)]}, None, vol,
                        vrec.VesselOptions(), 2.0)  # fmt: skip
    return s, flags


def test_wall_points_where_the_inner_radius_was_capped_are_flagged_unresolved():
    s, flags = _flags_of(np.full((41, 16), 4.0), [(0.0, 6.0), (2.0, 8.0)])  # 2 voxels' radius: resolved
    unresolved = np.any(flags & vrec.FLAG_UNRESOLVED, axis=1)
    assert np.array_equal(unresolved, s <= 8.0)
    assert not np.any(flags[s > 8.0])  # the rest covered: no other flag fires on this wall


def test_a_radius_with_fewer_voxels_than_the_velocity_priors_free_modes_is_unresolved():
    # the default basis (angular order 4) leaves 2 * 4 + 1 = 9 modes to the data: pi (R/h)^2 >= 9 voxels needs
    # R >= sqrt(9 / pi) h = 1.693 h
    assert vrec.min_radius_voxels(v3.Velocity3DOptions()) == pytest.approx(np.sqrt(9 / np.pi), rel=1e-12)
    assert vrec.min_radius_voxels(v3.Velocity3DOptions(angular_order=2)) == pytest.approx(np.sqrt(5 / np.pi))
    assert vrec.min_radius_voxels(v3.Velocity3DOptions(angular_order=0)) == vrec.MIN_RADIUS_VOXELS  # the floor
    radius = np.tile(np.linspace(2.0, 5.0, 41)[:, None], (1, 16))  # 1 to 2.5 voxels of 2 mm along the wall
    s, flags = _flags_of(radius, [])
    expected = radius < np.sqrt(9 / np.pi) * 2.0
    assert expected.any() and not expected.all()
    assert np.array_equal(flags == vrec.FLAG_UNRESOLVED, expected)
    assert not np.any(flags[~expected])


# ------------------------------------------------------------------ the band (velocity noise)
@pytest.fixture(scope="module")
def small_band(small_problem, small_wall):
    """The velocity fit on the small wall, its WSS at 16 angles and the band, with component noise scales 1, 0.8,
    1.5 (as three different vencs would give) to check the components' weighting."""
    vol, _, problem = small_problem
    vopt = v3.Velocity3DOptions(beta=1e-4)
    vp = v3.assemble(vol, small_wall, problem.frame, problem.coords, vopt, static_level=None)
    vel = v3.fit_velocity(vol, vp, vopt)
    s, phi = wss3d.wall_grid(small_wall.s_range, 2.5, 16)
    ss, pp = (v.ravel() for v in np.meshgrid(s, phi, indexing="ij"))
    pieces = wss3d.wall_pieces(problem.centerline, small_wall, vel.basis, ss, pp)
    ev = wss3d.wall_wss(problem.centerline, small_wall, vel, ss, pp, mu=MU, pieces=pieces)
    shape = (s.size, phi.size)
    ring = vrec.ring_weights(small_wall, s, phi, small_wall.radius(ss, pp).reshape(shape))
    area = ev.area.reshape(shape) / ev.area.sum()
    sigma = v3.velocity_noise(vol, vp, problem.levels) * np.array([1.0, 0.8, 1.5])
    with vrec.blas_threads(1):  # as the reconstruction runs it (small dense products: threads only cost)
        band = band3d.vessel_band(pieces, vel, sigma, ev.tau.reshape(1, *shape, 3), ring, area, MU)
    return {"vol": vol, "problem": problem, "vel": vel, "pieces": pieces, "ss": ss, "pp": pp, "ring": ring,
            "area": area, "sigma": sigma, "band": band, "shape": shape, "geometry": small_wall}  # fmt: skip


def test_the_band_matches_monte_carlo_refits_of_the_velocity(small_band, small_wall):
    """K re-fits on the same wall with fresh voxel noise of the std the band assumes (seeded): the sample std of
    the axial WSS at every wall point, of each plane's mean |tau| and of the wall's mean |tau| lies within the
    chi-square sampling tolerance of the predicted std: for K samples the relative std of a sample std is
    1 / sqrt(2 (K - 1)) = 0.035 at K = 400; 4.5 of those (0.16) over ~300 points."""
    import dataclasses

    b = small_band
    vel, vp = b["vel"], b["vel"].problem
    u = v3.voxel_velocities(b["vol"], vp)[0]
    k = 400
    rng = np.random.default_rng(11)
    noisy = u[None] + rng.standard_normal((k, *u.shape)) * b["sigma"][None]
    rhs = np.concatenate([vp.rhs(noisy[i]) for i in range(k)], axis=1)
    from scipy.linalg import cho_solve_banded

    with vrec.blas_threads(1):
        coef = cho_solve_banded((vp.factor(vel.beta), False), rhs).reshape(vp.size, k, 3).transpose(1, 0, 2)
    ev = wss3d.wall_wss(b["problem"].centerline, small_wall, dataclasses.replace(vel, coefficients=coef), b["ss"],
                        b["pp"], mu=MU, pieces=b["pieces"])  # fmt: skip
    tol = 4.5 / np.sqrt(2 * (k - 1))
    band = b["band"]
    ratio = ev.axial.std(axis=0, ddof=1) / band.axial_std_pa[0].ravel()
    assert np.all(np.abs(ratio - 1) < tol), (ratio.min(), ratio.max())
    mag = np.linalg.norm(ev.tau, axis=2).reshape(k, *b["shape"])
    planes = np.einsum("kij,ij->ki", mag, b["ring"]).std(axis=0, ddof=1) / band.plane_mean_std_pa[0]
    assert np.all(np.abs(planes - 1) < tol), (planes.min(), planes.max())
    wall = np.einsum("kij,ij->k", mag, b["area"]).std(ddof=1) / band.mean_std_pa
    assert abs(wall - 1) < tol, wall


def test_the_mean_wss_derivatives_in_beta_and_kappa_match_central_differences(small_band, small_wall):
    """d mean/d beta = -(H^-1 g)^T G_lap a / (pi L) (and kappa_v's) against central differences of re-solves with
    beta (kappa_v) times 1 -+ 1e-3: the difference's truncation error is O(1e-6) relative; 1e-4 leaves room for
    the re-solves' rounding."""
    import dataclasses

    b = small_band
    vel, vp = b["vel"], b["vel"].problem
    u = v3.voxel_velocities(b["vol"], vp)[0]

    def mean_at(beta, kappa):
        p = dataclasses.replace(vp, kappa=kappa)
        with vrec.blas_threads(1):
            coef = p.solve(beta, u).reshape(1, p.size, 3)
        ev = wss3d.wall_wss(b["problem"].centerline, small_wall, dataclasses.replace(vel, coefficients=coef),
                            b["ss"], b["pp"], mu=MU, pieces=b["pieces"])  # fmt: skip
        return float(np.linalg.norm(ev.tau[0], axis=1) @ b["area"].ravel())

    band, eps = b["band"], 1e-3
    assert mean_at(vel.beta, vp.kappa) == pytest.approx(band.mean_pa, rel=1e-12)
    beta, kappa = vel.beta, vp.kappa
    fd_beta = (mean_at(beta * (1 + eps), kappa) - mean_at(beta * (1 - eps), kappa)) / (2 * eps * beta)
    fd_kappa = (mean_at(beta, kappa * (1 + eps)) - mean_at(beta, kappa * (1 - eps))) / (2 * eps * kappa)
    assert band.d_mean_d_beta == pytest.approx(fd_beta, rel=1e-4) and band.d_mean_d_beta != 0
    assert band.d_mean_d_kappa == pytest.approx(fd_kappa, rel=1e-4) and band.d_mean_d_kappa != 0


def test_without_a_venc_the_band_is_nan_with_a_note(small_band):
    b = small_band
    vol = b["vol"]
    blind = VolumeAcquisition(vol.magnitude, vol.velocity, vol.affine_mm, None, vol.viscosity_pa_s, source="blind.h5")
    tau = np.zeros((1, *b["shape"], 3))
    axial, planes, record = vrec.wall_band(blind, b["vel"], b["problem"].levels, b["pieces"], tau, b["ring"],
                                           b["area"], np.zeros(b["shape"], np.uint8), MU)  # fmt: skip
    assert np.all(np.isnan(axial)) and axial.shape == (1, *b["shape"]) and np.all(np.isnan(planes))
    assert record["available"] is False and "velocity encoding (venc)" in record["note"]


def test_the_band_round_trips_and_older_files_still_read(arc_result, tmp_path):
    import h5py

    _, _, res, _ = arc_result
    path = tmp_path / "result.h5"
    vrec.write_result(path, res, mode="w")
    back = vrec.read_result(path)
    assert np.array_equal(back.axial_std_pa, res.axial_std_pa) and back.band == res.band
    assert np.array_equal(back.planes["mean_wss_std_pa"], res.planes["mean_wss_std_pa"])
    with h5py.File(path, "a") as f:  # the layout before the band
        del f["vessel/wss/axial_std_pa"], f["vessel/planes/mean_wss_std_pa"]
        del f["vessel"].attrs["band"]
    old = vrec.read_result(path)
    assert old.axial_std_pa is None and old.band == {} and "mean_wss_std_pa" not in old.planes
    assert old.plane_table().splitlines()[0] == "s_mm,area_mm2,flow_ml_s,mean_wss_pa,mean_axial_pa,flags"


def test_a_cine_band_keeps_each_frames_noise_independent(small_band):
    """Two frames, the fit times 1 and -0.5 (reverse flow): the axial band and each plane's band are the same in
    both frames (a reversed direction has the same variance), the frames' mean |tau| has std/sqrt(2) (two
    independent frames of equal variance, halved) and d mean/d beta = (1 + 0.5)/2 times the one frame's, by hand."""
    import dataclasses

    b = small_band
    vel, one = b["vel"], b["band"]
    scale = np.array([1.0, -0.5])
    two = dataclasses.replace(vel, coefficients=scale[:, None, None] * vel.coefficients[0])
    tau = np.stack([s * _tau(b) for s in scale])
    with vrec.blas_threads(1):
        cine = band3d.vessel_band(b["pieces"], two, b["sigma"], tau, b["ring"], b["area"], MU)
    assert np.allclose(cine.axial_std_pa, one.axial_std_pa[0], rtol=1e-12, atol=0)
    assert np.allclose(cine.plane_mean_std_pa, one.plane_mean_std_pa[0], rtol=1e-10, atol=0)
    assert cine.mean_std_pa == pytest.approx(one.mean_std_pa / np.sqrt(2), rel=1e-10)
    assert cine.mean_pa == pytest.approx(0.75 * one.mean_pa, rel=1e-12)
    assert cine.d_mean_d_beta == pytest.approx(0.75 * one.d_mean_d_beta, rel=1e-10)


def _tau(b):
    ev = wss3d.wall_wss(b["problem"].centerline, b["geometry"], b["vel"], b["ss"], b["pp"], mu=MU, pieces=b["pieces"])
    return ev.tau.reshape(*b["shape"], 3)


def test_the_band_under_the_temporal_prior_matches_monte_carlo_refits(small_band, small_wall):
    """Four frames (the fit's data times 1, 0.5, -0.3, 0.8) tied by the temporal prior (gamma 3, which takes the
    band at a wall point to about 0.6 of the frames' own): K = 300 re-fits through the prior with fresh voxel noise
    in every frame (seeded). The sample std of the axial WSS at every wall point and frame and of the wall's mean
    |tau| over the frames (the frames' noise now correlated) lie within the chi-square tolerance of the prediction
    (4.5 / sqrt(2 (K - 1)) = 0.18); d mean / d beta equals central differences of re-solves through the prior
    (1e-4, as for one frame); gamma -> 0 gives the frames' own band back (the eigenvector route: 1e-5)."""
    import dataclasses

    from wss_nlp.vessel import cycle3d

    b = small_band
    vel, vp = b["vel"], b["vel"].problem
    u = v3.voxel_velocities(b["vol"], vp)[0]
    scale = np.array([1.0, 0.5, -0.3, 0.8])
    n, k, gamma = scale.size, 300, 3.0
    mass = cycle3d.mass_gram(vp)
    import scipy.linalg

    mu, x = scipy.linalg.eigh(vp.hessian(vel.beta), mass)
    lam, mult = cycle3d.temporal_eigenvalues(n), cycle3d.mode_multiplicity(n)
    prior = band3d.TemporalPrior(gamma, mu, x, lam, mult)

    def fit(data, beta=vel.beta):  # data (n, V, 3 m) -> coefficients (n, size, 3 m)
        rhs = np.stack([vp.rhs(data[t]) for t in range(n)])
        with vrec.blas_threads(1):
            return cycle3d.solve_prior(vp, beta, gamma, rhs, mass)

    def wall(coef):  # (frames, size, 3) -> WallEvaluation
        return wss3d.wall_wss(b["problem"].centerline, small_wall, dataclasses.replace(vel, coefficients=coef),
                              b["ss"], b["pp"], mu=MU, pieces=b["pieces"])  # fmt: skip

    clean = fit(scale[:, None, None] * u[None])
    tau = wall(clean).tau.reshape(n, *b["shape"], 3)
    tied = dataclasses.replace(vel, coefficients=clean)
    with vrec.blas_threads(1):
        band = band3d.vessel_band(b["pieces"], tied, b["sigma"], tau, b["ring"], b["area"], MU, prior)
        alone = band3d.vessel_band(b["pieces"], tied, b["sigma"], tau, b["ring"], b["area"], MU)
        near0 = band3d.vessel_band(b["pieces"], tied, b["sigma"], tau, b["ring"], b["area"], MU,
                                   band3d.TemporalPrior(1e-9, mu, x, lam, mult))  # fmt: skip
    assert np.allclose(near0.axial_std_pa, alone.axial_std_pa, rtol=1e-5)
    assert near0.mean_std_pa == pytest.approx(alone.mean_std_pa, rel=1e-5)
    assert np.median(band.axial_std_pa / alone.axial_std_pa) < 0.8  # the prior matters here
    rng = np.random.default_rng(12)
    noise = rng.standard_normal((n, k, *u.shape)) * b["sigma"][None, None]
    data = (scale[:, None, None, None] * u[None, None] + noise).transpose(0, 2, 1, 3).reshape(n, u.shape[0], 3 * k)
    coef = fit(data).reshape(n, vp.size, k, 3)
    axial = np.empty((n, k, b["ss"].size))
    means = np.zeros(k)
    for t in range(n):
        ev = wall(coef[t].transpose(1, 0, 2))
        axial[t] = ev.axial
        means += np.linalg.norm(ev.tau, axis=2) @ b["area"].ravel() / n
    tol = 4.5 / np.sqrt(2 * (k - 1))
    ratio = axial.std(axis=1, ddof=1) / band.axial_std_pa.reshape(n, -1)
    assert np.all(np.abs(ratio - 1) < tol), (ratio.min(), ratio.max())
    wall_ratio = means.std(ddof=1) / band.mean_std_pa
    assert abs(wall_ratio - 1) < tol, wall_ratio

    def mean_at(beta):  # the wall mean over the frames of the prior's fit at this beta
        mag = np.linalg.norm(wall(fit(scale[:, None, None] * u[None], beta)).tau, axis=2)  # (n, points)
        return float(np.mean(mag @ b["area"].ravel()))

    assert mean_at(vel.beta) == pytest.approx(band.mean_pa, rel=1e-12)
    eps = 1e-3
    fd = (mean_at(vel.beta * (1 + eps)) - mean_at(vel.beta * (1 - eps))) / (2 * eps * vel.beta)
    assert band.d_mean_d_beta == pytest.approx(fd, rel=1e-4) and band.d_mean_d_beta != 0
