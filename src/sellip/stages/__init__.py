"""Stage functions: each reads its inputs from disk, calls the numerical kernels and writes its outputs.

Every Snakemake rule calls exactly one of these through the ``sellip`` command line.
"""
