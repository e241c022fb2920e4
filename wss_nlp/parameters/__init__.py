"""Noise estimation and parameter choice: one home for everything that picks alpha and beta from the data.

* :mod:`~wss_nlp.parameters.noise`: the noise levels of the magnitude and the velocity;
* :mod:`~wss_nlp.parameters.rules`: the rules (discrepancy, balancing, GCV, L-curve) on problem objects;
* :mod:`~wss_nlp.parameters.choice`: the rules applied to a slice's geometry and velocity problems
  (``choose_alpha``, ``choose_beta``), the near-wall model choice and the k-space filter choice.

Nothing is imported here, so the numerical modules can use :mod:`noise` and :mod:`rules` without importing
the pipeline that :mod:`choice` serves.
"""
