"""The uncertainty band against Monte Carlo

The band ``tau_std`` comes from CasADi's exact sensitivities of the whole chain (geometry KKT system,
velocity normal equations, WSS) and the estimated noise of every voxel. Here it is compared with the
spread of 40 reconstructions of the same slice with fresh noise (beta held fixed, as the linearization
does). The test suite runs the same comparison with 200 draws (``tests/test_sensitivity.py``).
"""

import numpy as np

from wss_nlp.parameters.options import ChoiceOptions
from wss_nlp.synthetic import phantoms
from wss_nlp.app import plotting
from wss_nlp.pipeline import ReconstructionOptions, reconstruct

clean, _ = phantoms.make_phantom("laminar", h_mm=1.5, snr=None, seed=2026)
rng = np.random.default_rng(2026)
banded = reconstruct(
    phantoms.noisy_copy(clean, 25.0, rng), ReconstructionOptions(choice=ChoiceOptions(beta_rule="fixed"))
)[0]
draws = 40
options = ReconstructionOptions(uncertainty=False, choice=ChoiceOptions(beta_rule="fixed"))
taus = np.array([reconstruct(phantoms.noisy_copy(clean, 25.0, rng), options)[0].wss.tau for _ in range(draws)])
sampled = taus.std(axis=0, ddof=1)
ratio = np.sqrt(np.mean(banded.wss.tau_std**2) / np.mean(sampled**2))
spread = 1 / np.sqrt(2 * draws)  # relative standard error of a sample standard deviation
print(f"rms band / rms Monte-Carlo spread: {ratio:.2f} ({draws} draws; sampling error about {spread:.0%})")

band = plotting.figure_band_check(banded.wss.phi, banded.wss.tau_std, sampled, draws)
