r"""What a near-wall layer family is: the interface every family module implements.

A family is the shape :math:`f` of the wall layer's columns
:math:`f(d/\ell)\,\rho^m (a_m\cos m\theta + b_m\sin m\theta)` of :mod:`wss_nlp.models.near_wall`, with
:math:`f(0) = 0` (the columns vanish on the wall) and :math:`f'(0) = 1` (a column's WSS is
:math:`\mu S/\ell` times its angular factor, whatever the family), and how its scale :math:`\ell` is found
from the data (:mod:`wss_nlp.parameters.layer`). The formulas are evaluated for NumPy arrays and for CasADi
symbols alike (the coupled method writes them into its NLP).

A new family is one module in this package that defines a :class:`WallFamily` subclass and registers an
instance (:func:`wss_nlp.models.families.register`); its name is then accepted by ``--near-wall``, the cell means
of the decoupled and coupled fits, the choice and the records.
"""

from __future__ import annotations

import casadi as ca
import numpy as np


class WallFamily:
    """A near-wall layer profile ``f(y)`` (``y = d / l``, ``y >= 0`` the fluid side) and how its scale is chosen.

    Attributes
    ----------
    name : str
        What ``--near-wall`` and the records call it.
    description : str
        One line for ``--help`` and the docs.
    scale_rule : {"consistent", "criterion"}
        "consistent": the scale is where the fitted layer obeys the law of the wall, :math:`u_\\tau\\ell = \\nu`
        (needs the kinematic viscosity; falls back to the criterion without it); "criterion": the scale that
        minimizes the BIC over a grid of scales.
    saturating : bool
        The profile saturates (laminar layers: entrance flow, Stokes layers); a chosen saturating layer
        thinner than the voxels resolve is a velocity jump, not a layer, and is refused (the slice is SUSPECT).
    turbulent : bool
        The family of turbulent flow: with ``--near-wall auto`` and a bulk Reynolds number known, turbulent
        flows (bulk Re above :data:`wss_nlp.models.near_wall.RE_TURBULENT`) try the turbulent families, laminar
        flows the others.
    reynolds_dependent : bool
        The profile's shape depends on the friction Reynolds number :math:`Re_\\tau = R/\\ell` (``R`` the lumen's
        mean radius): :meth:`at` gives the member at one, named ``"<name>@<Re_tau>"``
        (:func:`wss_nlp.models.families.at_reynolds`), and the layer machinery takes the member at each scale.
    supersedes : tuple of str
        Families this one is calibrated to replace: ``--near-wall auto`` tries it in their place (they stay
        available by name).
    """

    name: str = ""
    description: str = ""
    scale_rule: str = "criterion"
    saturating: bool = False
    turbulent: bool = False
    reynolds_dependent: bool = False
    supersedes: tuple[str, ...] = ()

    def f(self, y, lib):
        """``f(y)`` with the elementary functions of ``lib`` (``numpy`` or ``casadi``), ``y > -1/kappa``."""
        raise NotImplementedError

    def derivative(self, y: np.ndarray, order: int) -> np.ndarray:
        """``f^(order)(y)`` for ``order >= 1`` (NumPy; closed form)."""
        raise NotImplementedError

    def at(self, re_tau: float) -> WallFamily:
        """The profile at friction Reynolds number ``re_tau``: a family whose shape does not depend on it is
        itself."""
        return self

    def integrals(self, y, lib):
        """``(F_1, F_2)``: the first and second antiderivatives of ``f`` from 0, at ``y >= 0`` (``lib`` as in
        :meth:`f`)."""
        raise NotImplementedError


def library(y):
    """``casadi`` for CasADi symbols, ``numpy`` otherwise: the module whose ``log``, ``exp``, ... apply to ``y``."""
    return ca if isinstance(y, (ca.SX, ca.MX)) else np
