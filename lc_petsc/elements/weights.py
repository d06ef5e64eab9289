"""Continuum-consistent stiffness weights of the three energies (SPEC sections 1 and 2).

Cross-section of radius r: A = pi r^2, I = pi r^4 / 4, J = pi r^4 / 2. All functions are
elementwise over NumPy arrays (or scalars).
"""

import numpy as np


def stretch_stiffness(youngs, radius, rest_length):
    """k_s = E A / Lbar for an edge of mean radius ``radius``."""
    return youngs * np.pi * np.square(radius) / rest_length


def bend_stiffness(youngs, radius, voronoi_length):
    """k_b = E I / l_i at an interior vertex of radius ``radius``, l_i = (Lbar_{i-1} + Lbar_i)/2."""
    return youngs * 0.25 * np.pi * np.power(radius, 4) / voronoi_length


def twist_stiffness(shear, radius, rest_length):
    """k_t = G J / Lbar_mid for the middle edge (mean radius ``radius``) of a twist element."""
    return shear * 0.5 * np.pi * np.power(radius, 4) / rest_length
