"""Command-line interface: ``wss-nlp {demo, reconstruct, phantom, analyze, sensitivity, compare, export, import,
sweep, table, plot}``.

Exit codes: 0 success, 1 solver failure, 2 bad input or usage. One module per concept: :mod:`.parser`
(the arguments), :mod:`.main` (dispatch, errors, logging), one module per group of subcommands.
"""

from .main import main  # noqa: F401
from .parser import build_parser  # noqa: F401
from .arguments import options_from_args  # noqa: F401
from .report import sensitivity_table  # noqa: F401
