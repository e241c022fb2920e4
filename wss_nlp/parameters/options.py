"""The options of everything chosen from the data: alpha and beta rules, their factors, given noise levels.

:class:`ChoiceOptions` is the ``choice`` part of :class:`wss_nlp.pipeline.options.ReconstructionOptions`; the
command line spells its fields as before (``--alpha``, ``--beta``, ``--tau-beta``, ...), and the study keys too.
"""

from __future__ import annotations

from dataclasses import dataclass

from ..core.schema import option
from ..errors import InputError
from ..models.geometry import GeometryOptions
from ..models.velocity import VelocityOptions

ALPHA_RULES = ("fixed", "discrepancy", "balance")
BETA_RULES = ("fixed", "discrepancy", "gcv", "lcurve", "balance")
DEPHASING_BETA_RULES = ("gcv", "same")
#: What ``auto`` means for alpha and beta: the rule closest to the oracle in scripts/accuracy.py --auto (docs).
AUTO_RULE = "balance"

_DEFAULT_ALPHA = GeometryOptions().alpha
_DEFAULT_BETA = VelocityOptions().beta


def parse_rule(word: str, rules: tuple, name: str) -> str:
    """The rule a user's word names (``auto`` -> :data:`AUTO_RULE`); InputError lists the accepted words."""
    word = word.strip().lower()
    if word == "auto":
        return AUTO_RULE
    if word in rules and word != "fixed":
        return word
    words = ["auto"] + [r for r in rules if r != "fixed"]
    raise InputError(f"{name} must be a number or one of {', '.join(words)}; got {word!r}")


def _parameter_word(text, name: str) -> dict:
    """``--alpha`` / ``--beta`` (or a study key): a number is used as given (fixed rule), a word names a rule.

    Returns the option paths it sets, from the root options: the rule in ``choice``, the value in ``geometry``
    (alpha) or ``velocity`` (beta).
    """
    rules = ALPHA_RULES if name == "alpha" else BETA_RULES
    part = "geometry" if name == "alpha" else "velocity"
    try:
        return {f"choice.{name}_rule": "fixed", f"{part}.{name}": float(text)}
    except ValueError:
        return {f"choice.{name}_rule": parse_rule(str(text), rules, f"--{name}")}


@dataclass(frozen=True)
class ChoiceOptions:
    """How alpha and beta are chosen from the data (docs, "Choosing alpha and beta").

    ``alpha_rule`` / ``beta_rule``: "fixed" uses ``geometry.alpha`` / ``velocity.beta`` of the root options;
    "discrepancy" searches ``p0 2^-n`` for the largest value whose residual is at most ``tau`` times the
    estimated (or given) noise level, eqs. (disc), (disc2); "balance" is Lepskii's balancing principle (on the
    radius for alpha, on the WSS for beta; ``kappa_alpha``, ``kappa_beta``); for beta also "gcv" and "lcurve"
    (:mod:`wss_nlp.parameters.rules`). The defaults, beta by balancing and alpha fixed, and tau = 1.1 come
    from ``scripts/parameter_rules.py`` and ``scripts/accuracy.py --auto``: the balancing beta's worst case is
    far better than the former fixed beta's (laminar 1.48x against 2.70x the oracle, turbulent 5.5-25x against
    15-55x); for alpha balancing costs about three times a solve and gains nothing measurable over the fixed
    value.
    """

    schema_group = "method and parameter choice"

    alpha_rule: str = option(
        "fixed",
        "Tikhonov parameter of the H^s radius penalty (dimensionless), or a rule: "
        "'auto' = 'balance' (Lepskii balancing on the radius), 'discrepancy' (eq. (disc))",
        cli="--alpha",
        toml=("alpha",),
        parse=lambda text: _parameter_word(text, "alpha"),
        default_text=str(_DEFAULT_ALPHA),
        group=GeometryOptions.schema_group,
    )
    beta_rule: str = option(
        "balance",
        "Tikhonov parameter of the ||Delta^t v||^2 penalty (dimensionless, e.g. "
        f"{_DEFAULT_BETA:g}), or a rule: 'auto' = 'balance' (Lepskii balancing on the WSS; see "
        "docs), 'discrepancy' (eq. (disc2)), 'gcv' (generalized cross-validation), 'lcurve'",
        cli="--beta",
        toml=("beta",),
        parse=lambda text: _parameter_word(text, "beta"),
        default_text="auto",
        group=VelocityOptions.schema_group,
    )
    tau_alpha: float = option(
        1.1,
        "discrepancy factor for alpha (the paper's theory uses 4)",
        cli="--tau-alpha",
        toml=("tau_alpha",),
        group=GeometryOptions.schema_group,
    )
    tau_beta: float = option(
        1.1,
        "discrepancy factor for beta (the paper's theory uses 2)",
        cli="--tau-beta",
        toml=("tau_beta",),
        group=VelocityOptions.schema_group,
    )
    kappa_alpha: float = option(
        2.0,
        "balancing rule: radius differences allowed, in noise standard deviations",
        cli="--kappa-alpha",
        toml=("kappa_alpha",),
        group=GeometryOptions.schema_group,
    )
    # beta: noise alone stays below 2, but the least regularized WSS estimates carry a bias of their own (the
    # voxel means do not fix every coefficient), which the rule reads as bias of the more regularized ones; 2.5 is
    # the margin that absorbed it on held-out seeds (scripts/parameter_rules.py --kappa, docs)
    kappa_beta: float = option(
        2.5,
        "balancing rule: WSS differences allowed, in noise standard deviations",
        cli="--kappa-beta",
        toml=("kappa_beta",),
        group=VelocityOptions.schema_group,
    )
    alpha_start: float = 1.0
    beta_start: float = 1e-2
    noise_magnitude: float | None = option(
        None,
        "noise level delta of the normalized magnitude in mm (default: estimated)",
        cli="--noise-magnitude",
        group=GeometryOptions.schema_group,
    )
    noise_velocity: float | None = option(
        None,
        "noise level epsilon of the velocity in m/s (default: estimated)",
        cli="--noise-velocity",
        group=VelocityOptions.schema_group,
    )
    dephasing_beta_rule: str = option(
        "gcv",
        "beta of the velocity fit that predicts dephasing: GCV (keeps steep "
        "boundary layers) or the same beta as the WSS fit",
        cli="--dephasing-beta",
        choices=DEPHASING_BETA_RULES,
        group="wall shear stress (Sec. 4)",
    )

    def __post_init__(self):
        if self.alpha_rule not in ALPHA_RULES:
            raise InputError(f"alpha rule must be one of {ALPHA_RULES}, got {self.alpha_rule!r}")
        if self.dephasing_beta_rule not in DEPHASING_BETA_RULES:
            raise InputError(
                f"dephasing beta rule must be one of {DEPHASING_BETA_RULES}, got {self.dephasing_beta_rule!r}"
            )
        if self.beta_rule not in BETA_RULES:
            raise InputError(f"beta rule must be one of {BETA_RULES}, got {self.beta_rule!r}")
        for name in ("tau_alpha", "tau_beta", "kappa_alpha", "kappa_beta", "alpha_start", "beta_start"):
            if not getattr(self, name) > 0:
                raise InputError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("noise_magnitude", "noise_velocity"):
            val = getattr(self, name)
            if val is not None and not val > 0:
                raise InputError(f"{name} must be > 0, got {val}")

    def check_values(self, alpha: float, beta: float) -> None:
        """A value set next to a rule that would ignore it is a mistake to report, not to drop silently."""
        for name, rule, value, default in (
            ("alpha", self.alpha_rule, alpha, _DEFAULT_ALPHA),
            ("beta", self.beta_rule, beta, _DEFAULT_BETA),
        ):
            if rule != "fixed" and value != default:
                raise InputError(
                    f"{name} = {value:g} is set but the {name} rule is {rule!r}, which chooses {name} "
                    f"from the data; pass {name}_rule='fixed' (CLI: --{name} {value:g}) to use it"
                )

    #: The names these fields had on the root options before 0.2 (``ReconstructionOptions(beta_rule=...)``).
    FIELDS = (
        "alpha_rule", "beta_rule", "tau_alpha", "tau_beta", "kappa_alpha", "kappa_beta", "alpha_start",
        "beta_start", "noise_magnitude", "noise_velocity", "dephasing_beta_rule",
    )  # fmt: skip
