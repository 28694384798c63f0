"""Exact Riemann-Liouville differintegrals, evaluated independently in float64.

``alpha < 0`` is an integral of order ``-alpha``, ``alpha > 0`` a derivative; the
formulas below hold for both (they are the term-by-term RL images of power series).
"""

import mpmath
import numpy as np
import pymittagleffler
from scipy.special import gamma


def power(t: np.ndarray, beta: float, alpha: float) -> np.ndarray:
    """RL differintegral of order alpha of t**beta: Gamma(b+1)/Gamma(b+1-a) t**(b-a)."""
    out = np.zeros_like(t)
    pos = t > 0
    out[pos] = gamma(beta + 1) / gamma(beta + 1 - alpha) * t[pos] ** (beta - alpha)
    return out


def mittag_leffler(z: np.ndarray, a: float, b: float = 1.0) -> np.ndarray:
    return np.asarray(pymittagleffler.mittag_leffler(np.asarray(z, complex), a, b)).real


def sine(t: np.ndarray, omega: float, alpha: float) -> np.ndarray:
    """D^alpha sin(omega t) = omega t^(1-alpha) E_{2,2-alpha}(-omega^2 t^2)."""
    out = np.zeros_like(t)
    pos = t > 0
    tp = t[pos]
    out[pos] = omega * tp ** (1 - alpha) * mittag_leffler(-((omega * tp) ** 2), 2.0, 2.0 - alpha)
    return out


def cosine(t: np.ndarray, omega: float, alpha: float) -> np.ndarray:
    """D^alpha cos(omega t) = t^(-alpha) E_{2,1-alpha}(-omega^2 t^2)."""
    out = np.full_like(t, np.nan)
    pos = t > 0
    tp = t[pos]
    out[pos] = tp ** (-alpha) * mittag_leffler(-((omega * tp) ** 2), 2.0, 1.0 - alpha)
    if alpha < 0:
        out[~pos] = 0.0
    return out


def exp_imag_mpmath(t: float, omega: float, alpha: float) -> complex:
    """D^alpha exp(i omega t), alpha < 0, by the incomplete gamma function (mpmath).

    I^b exp(l t) = l^-b exp(l t) P(b, l t), P the regularized lower incomplete gamma.
    An evaluation independent of the Mittag-Leffler route, used to check it.
    """
    b = -alpha
    lam = 1j * omega
    with mpmath.workdps(40):
        val = (
            mpmath.power(lam, -b)
            * mpmath.exp(lam * t)
            * mpmath.gammainc(b, 0, lam * t, regularized=True)
        )
    return complex(val)
