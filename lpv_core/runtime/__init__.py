"""Process settings for the compute: compiled kernels (numba), heap and BLAS threads."""
