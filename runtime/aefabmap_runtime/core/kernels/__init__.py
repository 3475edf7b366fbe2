"""Compiled kernels and their switch (C via ctypes, numba, numpy fallbacks), packed bits, varints: what every stage stands on."""
