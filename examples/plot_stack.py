"""A stack of slices through a tapered tube

Six slices 2 mm apart through a tube whose radius shrinks along its axis, reconstructed together: the
z-regularization ties neighbouring slices' radius and velocity coefficients. The unrolled wall shows the
radius and the WSS over angle and slice position. Each slice's uncertainty band comes from the whole
segment's linearization (``wss_nlp.uncertainty.stack_band``: one slice's noise moves its neighbours too).
"""

import numpy as np

from wss_nlp.synthetic import phantoms
from wss_nlp.app import plotting
from wss_nlp.pipeline import ReconstructionOptions, reconstruct

acq, truth = phantoms.make_stack("tapered", nz=6, h_mm=1.5, spacing_mm=2.0, snr=25, seed=2026)
results = reconstruct(acq, ReconstructionOptions())
means = np.array([r.wss.mean for r in results])
stds = np.array([r.wss.mean_std for r in results])
exact = np.array([t.mean_wss for t in truth.slices])
print("mean WSS per slice [Pa]:", np.round(means, 3))
print("its band (1 std) [Pa]:  ", np.round(stds, 4))
print("exact [Pa]:             ", np.round(exact, 3))

stack = plotting.figure_stack(results, 2.0)
