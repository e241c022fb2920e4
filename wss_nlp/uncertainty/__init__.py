"""Derivatives of the reconstruction and the linearized uncertainty band (slices, stacks)."""
