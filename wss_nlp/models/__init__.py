"""The paper's models: measurement (forward) models, preprocessing, geometry, velocity, near-wall layers, WSS,
dephasing, the coupled NLP, z-coupled stacks, cycle models, the classical baselines.
"""
