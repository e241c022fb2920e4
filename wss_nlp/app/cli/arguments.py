"""The reconstruction options on the command line: declared once (:mod:`wss_nlp.core.schema`), read back here."""

from __future__ import annotations

import argparse

from ...core import schema
from ...pipeline.options import ReconstructionOptions


def _add_reconstruction_arguments(p: argparse.ArgumentParser) -> None:
    """Every reconstruction option, from the options schema (:mod:`wss_nlp.core.schema`)."""
    schema.add_arguments(p, ReconstructionOptions)


def options_from_args(args) -> ReconstructionOptions:
    return schema.from_args(ReconstructionOptions, args)
