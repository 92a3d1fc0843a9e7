"""PDM Score engine for NAVSIM v1.0, v1.1 (PDMS) and v2.2 (EPDMS): a pure library (numpy, shapely 2, scipy).

Importing it first selects the OpenBLAS kernels the official results were made with (`scorer.blas`).
"""

ENGINE_VERSION = "0.6.1"

from scorer.blas import select_devkit_kernels  # after ENGINE_VERSION, which it imports

select_devkit_kernels()
