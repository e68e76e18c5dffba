"""Slider-crank kinematics (pure numpy; tabulated once per operating point).

Reference: Heywood 1988, sec. 2.2, eqs 2.4-2.6.
"""

import numpy as np


def piston_position(theta_deg, stroke_m, conrod_m):
    """Piston distance below TDC [m] at crank angle theta [deg] (0 = TDC)."""
    a = stroke_m / 2.0
    th = np.radians(np.asarray(theta_deg, dtype=float))
    s = a * np.cos(th) + np.sqrt(conrod_m**2 - (a * np.sin(th)) ** 2)
    return conrod_m + a - s


def cylinder_volume(theta_deg, bore_m, stroke_m, conrod_m, compression_ratio):
    """Cylinder volume [m^3]: V = Vc + pi B^2/4 * x(theta)."""
    area = np.pi / 4.0 * bore_m**2
    vc = area * stroke_m / (compression_ratio - 1.0)
    return vc + area * piston_position(theta_deg, stroke_m, conrod_m)


def liner_area(theta_deg, bore_m, stroke_m, conrod_m, compression_ratio):
    """Exposed liner area [m^2]: pi*B*(x + h_c), h_c the clearance height Vc/(pi B^2/4)."""
    hc = stroke_m / (compression_ratio - 1.0)
    return np.pi * bore_m * (piston_position(theta_deg, stroke_m, conrod_m) + hc)


def mean_piston_speed(speed_rpm, stroke_m):
    """Mean piston speed [m/s] = 2 * stroke * N/60."""
    return 2.0 * stroke_m * np.asarray(speed_rpm, dtype=float) / 60.0
