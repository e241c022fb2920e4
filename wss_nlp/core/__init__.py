"""Numerics that know nothing of scanners: Fourier radius spaces, the disk map, wall bases, linear Tikhonov, BLAS
operators and pointwise ladders inside CasADi graphs, IPOPT plumbing, the options schema.
"""
