"""Background phase correction of 4D flow volumes (wss_nlp.vessel.background): each component's offset fitted on
static tissue, the lumen and flowing neighbours kept out (issue 39's correction for volumes)."""

import dataclasses

import numpy as np

from wss_nlp.io.volume import VolumeAcquisition
from wss_nlp.synthetic import vessels as vs
from wss_nlp.vessel import background as bg
from wss_nlp.vessel import segmentation


def _world(vol):
    a = np.asarray(vol.affine_mm, float)
    idx = np.indices(vol.shape).reshape(3, -1).T
    return (idx @ a[:3, :3].T + a[:3, 3]).reshape(*vol.shape, 3)


def _offset_field(vol, rng, percent=2.0):
    """A smooth offset per component (linear plus a cross term), ``percent`` % of the venc at the view's centre."""
    x = _world(vol)
    u = (x - x.reshape(-1, 3).mean(axis=0)) / 50.0
    venc = np.asarray(vol.venc_m_s, float)
    return np.stack([percent / 100 * venc[c] * (1 + u @ rng.uniform(-0.8, 0.8, 3) + 0.3 * u[..., 0] * u[..., 1])
                     for c in range(3)])  # fmt: skip


def test_the_offset_of_a_vessel_in_tissue_is_removed_in_its_lumen():
    """The arch in tissue (h = 2 mm, SNR 20, development seed 2) with a 2 % venc offset in each component. Left in
    the lumen after the correction: on average at most 0.1 % of the venc (measured 0.017 % at most), its RMS
    within twice what the record predicts (the fit's std or its change with one order more; measured 0.05-0.18 %
    against 0.06-0.14 %: the record's uncertainty is honest), nowhere more than 1 % (uncorrected: 2 % and more).
    Where the prediction exceeds 0.1 % of the venc the record says uncertain (here it does)."""
    vol, _ = vs.make_vessel_phantom("arc", h_mm=2.0, snr=20, seed=2, tissue=True)
    field = _offset_field(vol, np.random.default_rng(5))
    shifted = dataclasses.replace(vol, velocity=vol.velocity + field[None])
    lumen = segmentation.segment_vessel(shifted).mask
    fixed, rec = bg.correct_volume(shifted, lumen)
    assert rec.applied and rec.static_voxels > 5000, rec
    venc = np.asarray(vol.venc_m_s, float)
    left = (fixed.velocity[0] - vol.velocity[0])[:, lumen] / venc[:, None]  # the offset left, per component
    predicted = np.maximum(rec.lumen_std_m_s, rec.lumen_spread_m_s) / venc
    assert np.max(np.abs(left.mean(axis=1))) <= 1e-3, left.mean(axis=1)
    assert np.all(np.sqrt(np.mean(left**2, axis=1)) <= 2 * predicted), (np.sqrt(np.mean(left**2, axis=1)), predicted)
    assert np.max(np.abs(left)) <= 1e-2
    assert rec.uncertain == bool(np.max(predicted) > 1e-3)
    assert "background offset removed" in rec.note() and ("uncertain" in rec.note()) == rec.uncertain


def test_a_volume_without_static_tissue_is_left_as_it_is():
    # a tube in air: nothing static to fit; the volume object itself comes back, so the results are unchanged
    vol, _ = vs.make_vessel_phantom("straight", h_mm=2.5, snr=20, seed=1, visible_mm=(20.0, 40.0), radius_mm=6.0)
    lumen = segmentation.segment_vessel(vol).mask
    fixed, rec = bg.correct_volume(vol, lumen)
    assert fixed is vol and not rec.applied and rec.reason.startswith("no static tissue") and rec.note() is None


def test_a_flowing_neighbour_is_not_static_tissue():
    # static tissue with a linear offset, the main vessel (the mask) and a second vessel flowing at 0.3 m/s that
    # no mask names: the fit keeps the neighbour out (its speed is 30 noise deviations of the mean) and recovers
    # the offset in the main lumen to 0.1 % of the venc; with the neighbour taken as static it would be ~1 %
    rng = np.random.default_rng(11)
    shape, h, venc = (36, 36, 24), 2.0, 1.0
    affine = np.diag([h, h, h, 1.0])
    i, j, _ = np.indices(shape)
    x, y = (i - 17.5) * h, (j - 17.5) * h
    main = np.hypot(x, y) < 10.0
    other = np.hypot(x - 22.0, y - 22.0) < 7.0
    magnitude = np.where(main | other, 1.0, 0.4)
    flow = np.zeros((3, *shape))
    flow[2][main] = 0.8 * (1 - (np.hypot(x, y)[main] / 10.0) ** 2)
    flow[2][other] = 0.3
    vol = VolumeAcquisition(magnitude[None], flow[None], affine, (venc,) * 3, 3.5e-3)
    offset = np.stack([0.02 * venc * (1 + 0.4 * x / 36 - 0.3 * y / 36), 0.015 * venc * (1 + 0.5 * y / 36),
                       0.02 * venc * np.ones(shape)])  # fmt: skip
    noise = 0.01 / magnitude  # phase noise k / M: SNR 10 in the tissue (venc 1 m/s), 31 in the lumen
    measured = flow + offset + rng.normal(size=flow.shape) * noise
    fixed, rec = bg.correct_volume(dataclasses.replace(vol, velocity=measured[None]), main)
    assert rec.applied, rec
    left = (fixed.velocity[0] - measured)[:, main] + offset[:, main]  # true offset minus fitted, in the lumen
    assert np.max(np.abs(left.mean(axis=1))) <= 1e-3 * venc, left.mean(axis=1)
    # the noise scale k is estimated from the static voxels' high-pass within 10 %
    assert abs(rec.noise_k / 0.01 - 1) < 0.1, rec.noise_k
