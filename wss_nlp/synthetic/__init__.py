"""Synthetic data with exact truth: phantoms that the reconstructions are validated on."""
