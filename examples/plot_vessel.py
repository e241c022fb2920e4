"""A curved vessel from a 4D flow volume: the WSS map over its wall

A 4D flow phantom of an arch-shaped vessel (radius 8 mm, a 180 degree arc of radius 30 mm with straight legs;
the grid turned at random against it), 2.5 mm voxels, SNR 20, one frame, as ``wss-nlp phantom --volume-case arc``
writes it. ``reconstruct_vessel`` segments the lumen, finds the centreline, fits the wall ``R(s, phi)`` and the
three velocity components to the volume's own voxels and evaluates the WSS vector from exact derivatives
(docs: "4D flow"). Beside it, on the same segmentation, the wall-normal fit most 4D flow tools use
(``wss_nlp.vessel.baseline``). Both are measured against the phantom's exact WSS (``wss_nlp.vessel.metrics``).
The figures are what ``reconstruct --figures`` saves: the wall unrolled (arc length x angle) and a 3D view.
A small case so that the docs build quickly; the accuracy table over five seeds and five vessel shapes is
``scripts/results/vessel_accuracy.md``.
"""

from wss_nlp.app import plotting
from wss_nlp.synthetic.vessels import make_vessel_phantom
from wss_nlp.vessel.baseline import baseline_vessel
from wss_nlp.vessel.metrics import accuracy
from wss_nlp.vessel.reconstruct import reconstruct_vessel, vessel_inputs

vol, truth = make_vessel_phantom("arc", h_mm=2.5, snr=20, seed=2026, radius_mm=8.0)
print(f"volume {vol.shape} voxels of {vol.voxel_size_mm[0]} mm, venc {vol.venc_m_s[0]} m/s")

inputs = vessel_inputs(vol)  # the lumen mask (PC-MRA) and the centreline, from the data
result = reconstruct_vessel(vol, inputs=inputs)
base = baseline_vessel(vol, inputs.mask, inputs.centerline, inputs.record, s=result.s_mm, phi=result.phi)
ours, theirs = accuracy(result, truth), accuracy(base, truth)

print(f"{'':34s}{'reconstruction':>16s}{'wall-normal fit':>17s}")
print(f"{'WSS vector, rel. L2 error':34s}{ours.wss_rel_l2:>16.1%}{theirs.wss_rel_l2:>17.1%}")
print(f"{'wall RMS distance / h':34s}{ours.wall_rms_mm / 2.5:>16.3f}{theirs.wall_rms_mm / 2.5:>17.3f}")
print(f"{'visible wall covered':34s}{ours.coverage:>16.1%}{theirs.coverage:>17.1%}")
print(f"{'mean WSS [Pa] (exact ' + format(ours.true_mean_wss_pa, '.3f') + ')':34s}"
      f"{ours.mean_wss_pa:>16.3f}{theirs.mean_wss_pa:>17.3f}")  # fmt: skip

wall_map = plotting.figure_vessel_wall_map(result)
wall_3d = plotting.figure_vessel_wall_3d(result)
