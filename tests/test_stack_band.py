"""The uncertainty band of z-regularized stacks (uncertainty.stack_band): derivatives against re-solves of the stack,
the weakly coupled limit against the slice band of wss_nlp.uncertainty.sensitivity (an independent implementation)."""

from dataclasses import replace

import numpy as np
import pytest

from wss_nlp.pipeline import driver
from wss_nlp.parameters.options import ChoiceOptions
from wss_nlp.models import geometry as geo
from wss_nlp.synthetic import phantoms
from wss_nlp.models import stack
from wss_nlp.uncertainty import stack_band
from wss_nlp.core import radius as rad
from wss_nlp.models import velocity as vel
from wss_nlp.models import wss as wss_mod
from wss_nlp.pipeline import ReconstructionOptions, reconstruct

# Re-solves at IPOPT tol 1e-13 (geometry) and exact normal equations (velocity); central differences with a step
# of 1e-4 (normalized magnitude, m/s) are then accurate to ~1e-7 relative, so 1e-4 is far from rounding and far
# below any modelling error a wrong coupling term would cause (the cross-slice responses below are 10-60 % of
# the slice's own).
RTOL = 1e-4
N_PHI = 90


class StackPipeline:
    """The z-coupled geometry and velocity solves of a segment, re-run with one slice's data changed."""

    def __init__(self, results, info, mu, order=1, r1=None):
        self.res, self.mu, self.order, self.r1 = results, mu, order, r1 or {}
        self.kappa, self.kappa_v = info.kappa, info.kappa_velocity
        self.gopt = geo.GeometryOptions(tol=1e-13)
        self.vopt = vel.VelocityOptions(solver="cholesky", near_wall="off")
        self.betas = [r.velocity.beta for r in results]
        self.x0 = np.array([r.geometry.coefficients for r in results])
        self.base = self.solve()

    def problem(self, k, m=None):
        r = self.res[k]
        lum, m = r.lumen, r.magnitude if m is None else m
        return geo.GeometryProblem(r.grid, m, lum.center, lum.r0, self.r1.get(k, lum.r1), lum.r_area)

    def solve(self, j=None, dm=None, du=None):
        problems = [self.problem(k, r.magnitude + dm if (k == j and dm is not None) else None) for k, r in
                    enumerate(self.res)]  # fmt: skip
        sg = [stack.SliceGeometry(pb, self.gopt, self.kappa) for pb in problems]
        coef, _ = stack.coupled_geometry(sg, self.gopt.alpha, self.x0, self.order)
        geoms = [geo.finish(pb, self.gopt, s.nlp, c, None, self.gopt.alpha) for pb, s, c in zip(problems, sg, coef)]
        images = [r.velocity_image + du if (k == j and du is not None) else r.velocity_image for k, r in
                  enumerate(self.res)]  # fmt: skip
        vps = [vel.assemble(r.grid, u, g.coefficients, g.center, self.vopt) for r, u, g in zip(self.res, images, geoms)]
        gram0 = vps[0].basis.laplacian_gram(0)
        vcoef, st = stack.coupled_velocity(vps, self.betas, self.kappa_v, gram0, self.order)
        taus = [
            wss_mod.from_reconstruction(vel.result(vp, self.vopt, c, b, st), N_PHI, self.mu).tau
            for vp, c, b in zip(vps, vcoef, self.betas)
        ]
        return problems, sg, geoms, vps, vcoef, np.array(taus)

    def linearization(self):
        problems, sg, geoms, vps, vcoef, _ = self.base
        slices = [
            stack_band.BandSlice(pb, g, s.lam_g, vp, c, b)
            for pb, g, s, vp, c, b in zip(problems, geoms, sg, vps, vcoef, self.betas)
        ]
        return stack_band.linearize(slices, self.gopt, self.vopt, self.mu, N_PHI)

    def covariances(self, lin, info_m, info_u):
        n = len(self.res)
        basis = self.base[3][0].basis
        return lin.covariances(
            info_m, info_u, self.kappa, self.kappa_v, stack.z_operator(n, self.order),
            rad.sobolev_weights(self.gopt.n_fourier, 0), basis.laplacian_gram(0),
        )  # fmt: skip


@pytest.fixture(scope="module", params=[(1, False), (2, False), (2, True)], ids=["order1", "order2", "order2-box"])
def segment(request):
    """A 5-slice segment (z order 1 or 2); "box": slice 2's upper radius bound 0.3 mm below its fitted wall, so
    its box rows are active and enter the joint system."""
    order, box = request.param
    acq, _ = phantoms.make_stack("curved", nz=5, h_mm=1.5, spacing_mm=2.0, snr=15, seed=7)
    opts = ReconstructionOptions(uncertainty=False, dephasing_correction=False)
    opts = replace(opts, velocity=replace(opts.velocity, near_wall="off"))
    st = stack.StackOptions(strategy="coupled", z_smoothing_mm=3.0, z_order=order)
    res, info = driver.reconstruct_stack(acq, opts, st)
    r1 = {}
    if box:
        r1[2] = float(np.max(res[2].geometry.radius(np.linspace(0, 2 * np.pi, 720)))) - 0.3
    pipe = StackPipeline(res, info, acq.viscosity_pa_s, order, r1)
    assert np.count_nonzero(pipe.base[1][2].lam_g) > 0 if box else True
    return pipe


def _zeros(lin):
    return [np.zeros((h.shape[0],) * 2) for h in lin.hessians], [np.zeros((h.shape[0],) * 2) for h in lin.normal]


def test_recursion_equals_the_dense_inverse(segment):
    """The block-tridiagonal recursion gives the diagonal blocks of A^-1 S A^-T that the dense inverse of the
    assembled joint system gives (random positive semidefinite S per slice). The joint matrix's condition number
    is up to 3e11 here (KKT scaling), so the dense reference carries rounding up to ~1e-5 in the worst case;
    observed: 3e-13 relative; 1e-9 is the tolerance."""
    lin = segment.linearization()
    n = len(segment.res)
    zop = stack.z_operator(n, segment.order)
    w0, gram0 = rad.sobolev_weights(segment.gopt.n_fourier, 0), segment.base[3][0].basis.laplacian_gram(0)
    rng = np.random.default_rng(3)

    def psd(k):
        a = rng.normal(size=(k, k))
        return a @ a.T

    info_m = [psd(h.shape[0]) for h in lin.hessians]
    info_u = [psd(h.shape[0]) for h in lin.normal]
    block, sizes = stack_band.joint_blocks(lin, segment.kappa, segment.kappa_v, zop, w0, gram0)
    dense = np.block([[block(k, j) for j in range(n)] for k in range(n)])
    inv = np.linalg.inv(dense)
    offsets = np.r_[0, np.cumsum([sum(sz) for sz in sizes])]
    covs = lin.covariances(info_m, info_u, segment.kappa, segment.kappa_v, zop, w0, gram0)
    for which, infos in ((0, info_m), (1, info_u)):
        s = np.zeros_like(dense)
        for k, (nr, na, _) in enumerate(sizes):
            part = slice(offsets[k], offsets[k] + nr) if which == 0 else slice(offsets[k] + nr + na, offsets[k + 1])
            s[part, part] = infos[k]
        full = inv @ s @ inv.T
        for k, (nr, na, _) in enumerate(sizes):
            keep = np.r_[offsets[k] : offsets[k] + nr, offsets[k] + nr + na : offsets[k + 1]]
            ref = full[np.ix_(keep, keep)]
            np.testing.assert_allclose(covs[k][which], ref, rtol=0, atol=1e-9 * np.max(np.abs(ref)))


@pytest.mark.parametrize("data", ["magnitude", "velocity"])
def test_cross_slice_responses_match_resolves(segment, data):
    """A change of slice 1's data moves the WSS of every slice: the linearized response (a rank-one noise
    covariance along the change gives std_k = |d tau_k / dt|) equals central differences of re-solves of the
    whole z-coupled segment, on the slice itself and on its neighbours (z order 1 and 2, box inactive and
    active)."""
    lin = segment.linearization()
    j, rng, step = 1, np.random.default_rng(5), 1e-4
    shape = segment.res[j].magnitude.shape
    direction = rng.normal(size=shape)
    info_m, info_u = _zeros(lin)
    if data == "magnitude":
        g = lin.d_grad_m[j] @ direction.ravel()[lin.m_index[j]]
        info_m[j] = np.outer(g, g)
        plus, minus = segment.solve(j, dm=step * direction)[-1], segment.solve(j, dm=-step * direction)[-1]
    else:
        g = lin.p[j] @ direction.ravel()[lin.u_index[j]]
        info_u[j] = np.outer(g, g)
        plus, minus = segment.solve(j, du=step * direction)[-1], segment.solve(j, du=-step * direction)[-1]
    fd = np.abs(plus - minus) / (2 * step)
    covs = segment.covariances(lin, info_m, info_u)
    for k, (cov_m, cov_u) in enumerate(covs):
        jac = lin.jac_tau[k]
        std = np.sqrt(np.einsum("ij,jk,ik->i", jac, cov_m + cov_u, jac))
        np.testing.assert_allclose(std, fd[k], rtol=0, atol=RTOL * np.max(fd[j]))
    # the coupling is real: the neighbours respond by a sizeable fraction of the slice itself
    assert np.max(fd[j + 1]) > 0.05 * np.max(fd[j]) and np.max(fd[j - 1]) > 0.05 * np.max(fd[j])


def test_weakly_coupled_stack_band_equals_the_slice_band():
    """With a negligible z-weight (l = 1e-4 mm for 2 mm spacing: kappa ~ 1e-9) the segment's band is the band of
    each slice alone, computed by wss_nlp.uncertainty.sensitivity (its own KKT, anchor re-solve and chain rule) to 1e-6;
    with the real weight the band narrows (the z-penalty pools neighbouring slices)."""
    acq, _ = phantoms.make_stack("curved", nz=3, h_mm=1.5, spacing_mm=2.0, snr=15, seed=8)
    opts = ReconstructionOptions(dephasing_correction=False, choice=ChoiceOptions(beta_rule="fixed"))
    weak, _ = driver.reconstruct_stack(acq, opts, stack.StackOptions(strategy="kaczmarz", z_smoothing_mm=1e-4))
    alone = reconstruct(acq, replace(opts, stack=stack.StackOptions(z_smoothing_mm=0.0)))
    for a, b in zip(weak, alone):
        assert not any("no uncertainty band" in n for n in a.notes)
        np.testing.assert_allclose(a.wss.tau_std, b.wss.tau_std, rtol=1e-6)
        assert a.wss.mean_std == pytest.approx(b.wss.mean_std, rel=1e-6)
    coupled, _ = driver.reconstruct_stack(acq, opts, stack.StackOptions(z_smoothing_mm=3.0))
    assert all(c.wss.mean_std < 0.95 * b.wss.mean_std for c, b in zip(coupled, alone))


def test_turbulent_stack_band_carries_the_wall_law_scale():
    """A turbulent stack (wall-law layer on every slice): the weakly coupled band equals the slice band, which
    includes the law-of-the-wall scale's response to the noise (wss_nlp.pipeline.band.slice_band), to 1e-6."""
    acq, _ = phantoms.make_stack("turbulent", nz=3, h_mm=1.5, spacing_mm=2.0, snr=25, seed=9)
    opts = ReconstructionOptions(dephasing_correction=False, choice=ChoiceOptions(beta_rule="fixed"))
    weak, _ = driver.reconstruct_stack(acq, opts, stack.StackOptions(strategy="kaczmarz", z_smoothing_mm=1e-4))
    alone = reconstruct(acq, replace(opts, stack=stack.StackOptions(z_smoothing_mm=0.0)))
    for a, b in zip(weak, alone):
        assert a.near_wall.model == b.near_wall.model == "low_re"
        assert a.near_wall.scale_ratio == pytest.approx(b.near_wall.scale_ratio, rel=1e-6)
        np.testing.assert_allclose(a.wss.tau_std, b.wss.tau_std, rtol=1e-6)
        assert a.near_wall.scale_std_log == pytest.approx(b.near_wall.scale_std_log, rel=1e-6)


@pytest.fixture(scope="module")
def coupled_segment():
    """A 4-slice segment solved by the coupled method (z order 2), with what a re-solve needs."""
    from wss_nlp.models.coupled import CoupledOptions

    acq, _ = phantoms.make_stack("curved", nz=4, h_mm=1.5, spacing_mm=2.0, snr=15, seed=17)
    opts = ReconstructionOptions(
        uncertainty=False,
        dephasing_correction=False,
        coupled=CoupledOptions(tol=1e-11),
        choice=ChoiceOptions(beta_rule="fixed"),
    )
    opts = replace(opts, velocity=replace(opts.velocity, near_wall="off"))
    res, info = driver.reconstruct_stack(acq, opts, stack.StackOptions(strategy="coupled", z_smoothing_mm=3.0))
    problems = [
        geo.GeometryProblem(r.grid, r.magnitude, r.lumen.center, r.lumen.r0, r.lumen.r1, r.lumen.r_area) for r in res
    ]
    starts = [(r.geometry, r.velocity) for r in res]

    def solve(j=None, dm=None, du=None):
        pbs = [replace(pb, magnitude=pb.magnitude + dm) if (k == j and dm is not None) else pb
               for k, pb in enumerate(problems)]  # fmt: skip
        images = [r.velocity_image + du if (k == j and du is not None) else r.velocity_image
                  for k, r in enumerate(res)]  # fmt: skip
        out, _ = stack.coupled_segment(
            pbs, images, starts, opts.geometry, opts.velocity, 0.7, [r.velocity.beta for r in res], info.kappa,
            info.kappa_velocity, 2, opts.coupled,
        )  # fmt: skip
        return out, np.array([wss_mod.from_reconstruction(c.velocity, N_PHI, acq.viscosity_pa_s).tau for c in out])

    return solve, problems, opts, info, acq.viscosity_pa_s, solve()


@pytest.mark.parametrize("data", ["magnitude", "velocity"])
def test_coupled_cross_slice_responses_match_resolves(coupled_segment, data):
    """The coupled method's segment band: the response of every slice's WSS to one voxel of slice 1 (noise on
    that voxel alone, std_k = |d tau_k / d voxel|) equals central differences of re-solves of the whole coupled
    segment (IPOPT at tol 1e-11) to 1e-4 of the slice's own response; the neighbours respond too."""
    solve, problems, opts, info, mu, (base, _) = coupled_segment
    j, step = 1, 1e-4
    n = len(problems)
    # a voxel on the wall (normalized magnitude nearest 0.5): the magnitude misfit and the velocity misfit's
    # precision weights both see it (voxels deep inside saturate both: no response to check)
    both = np.intersect1d(base[j].nlp.velocity_model.index, base[j].nlp.geometry.model.annulus)
    voxel = int(both[np.argmin(np.abs(problems[j].magnitude.ravel()[both] - 0.5))])
    e = np.zeros(problems[j].magnitude.shape)
    e.ravel()[voxel] = 1.0

    def levels(k, m_index, u_index):
        on = (k == j) * (m_index == voxel if data == "magnitude" else np.zeros(m_index.size, bool))
        on_u = (k == j) * (u_index == voxel if data == "velocity" else np.zeros(u_index.size, bool))
        return on.astype(float), on_u.astype(float)

    bands = stack_band.coupled_segment_band(
        base, problems, levels, opts.geometry, opts.velocity, info.kappa, info.kappa_velocity,
        stack.z_operator(n, 2), mu, N_PHI,
    )  # fmt: skip
    kw = {"dm": step * e} if data == "magnitude" else {"du": step * e}
    plus, minus = solve(j, **kw)[1], solve(j, **{k: -v for k, v in kw.items()})[1]
    fd = np.abs(plus - minus) / (2 * step)
    for k in range(n):
        np.testing.assert_allclose(bands[k].tau_std, fd[k], rtol=0, atol=1e-4 * np.max(fd[j]))
    assert np.max(fd[j + 1]) > 0.05 * np.max(fd[j])


def test_weakly_coupled_coupled_stack_band_equals_the_slice_band():
    """The coupled method with a negligible z-weight: each slice's segment band equals wss_nlp.uncertainty.sensitivity's
    coupled band of the slice alone (its own KKT system, polished by Newton steps) to 1e-6."""
    from wss_nlp.models.coupled import CoupledOptions

    acq, _ = phantoms.make_stack("curved", nz=3, h_mm=1.5, spacing_mm=2.0, snr=15, seed=12)
    opts = ReconstructionOptions(
        method="coupled",
        dephasing_correction=False,
        coupled=CoupledOptions(velocity_weight=0.5),
        choice=ChoiceOptions(beta_rule="fixed"),
    )
    weak = reconstruct(acq, replace(opts, stack=stack.StackOptions(z_smoothing_mm=1e-4)))
    alone = reconstruct(acq, replace(opts, stack=stack.StackOptions(z_smoothing_mm=0.0)))
    assert weak.stack is not None and alone.stack is None
    for a, b in zip(weak, alone):
        np.testing.assert_allclose(a.wss.tau_std, b.wss.tau_std, rtol=1e-6)
        assert a.wss.mean_std == pytest.approx(b.wss.mean_std, rel=1e-6)
