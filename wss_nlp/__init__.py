"""wss-nlp: vessel geometry, velocity and wall shear stress from phase-contrast MRI."""

__version__ = "0.1.0"
