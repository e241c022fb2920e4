"""How alpha and beta were chosen

Every result records its regularization parameters and how they were chosen. Here alpha by the
discrepancy principle (the geometry residual brought down to the estimated magnitude noise) and beta by
the default balancing principle on the WSS (the smallest beta whose WSS differs from the less
regularized ones by no more than their noise). The figures are those ``wss-nlp analyze --figures`` writes.
"""

from wss_nlp.parameters.options import ChoiceOptions
from wss_nlp.synthetic import phantoms
from wss_nlp.app import plotting
from wss_nlp.pipeline import ReconstructionOptions, reconstruct

acq, truth = phantoms.make_phantom("laminar", h_mm=1.0, snr=25, seed=2027)
res = reconstruct(acq, ReconstructionOptions(uncertainty=False, choice=ChoiceOptions(alpha_rule="discrepancy")))[0]
for choice in (res.alpha_choice, res.beta_choice):
    print(f"{choice.name}: {choice.chosen:.3g} by the {choice.rule} rule (noise estimate {choice.noise:.3g})")

alpha = plotting.figure_parameter_choice(res.alpha_choice)
beta = plotting.figure_parameter_choice(res.beta_choice)
