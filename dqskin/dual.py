"""Dual numbers ``a + eps b`` (``eps^2 = 0``) as ``(real, dual)`` pairs of arrays.

The two parts are NumPy arrays (or scalars) of any broadcastable shapes; every
function returns a ``(real, dual)`` tuple computed with NumPy broadcasting and
dtype rules. Division and square roots need a nonzero (for ``sqrt`` positive)
real part; otherwise the result holds the inf/NaN that NumPy produces.

References
----------
[K] B. Kenwright, "Dual-Quaternions: From Classical Mechanics to Computer
    Graphics and Beyond", 2012 (shared/references/000_e688072581e8ee3b.txt).
"""

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

__all__ = ["add", "mul", "div", "sqrt", "apply"]


def add(x: tuple[npt.ArrayLike, npt.ArrayLike],
        y: tuple[npt.ArrayLike, npt.ArrayLike]) -> tuple[np.ndarray, np.ndarray]:
    """Sum ``(a + eps b) + (c + eps d) = (a + c) + eps (b + d)`` ([K] eq. 19).

    ``x``, ``y``: (real, dual) pairs of array_like; returns a (real, dual) tuple of arrays.
    """
    return (np.add(x[0], y[0]), np.add(x[1], y[1]))


def mul(x: tuple[npt.ArrayLike, npt.ArrayLike],
        y: tuple[npt.ArrayLike, npt.ArrayLike]) -> tuple[np.ndarray, np.ndarray]:
    """Product ``(a + eps b)(c + eps d) = a c + eps (a d + b c)`` ([K] eq. 20).

    ``x``, ``y``: (real, dual) pairs of array_like; returns a (real, dual) tuple of arrays.
    """
    a, b = x
    c, d = y
    return (np.multiply(a, c), np.multiply(a, d) + np.multiply(b, c))


def div(x: tuple[npt.ArrayLike, npt.ArrayLike],
        y: tuple[npt.ArrayLike, npt.ArrayLike]) -> tuple[np.ndarray, np.ndarray]:
    """Quotient ``(a + eps b)/(c + eps d) = a/c + eps (b c - a d)/c^2`` ([K] eq. 21).

    Parameters
    ----------
    x, y : (real, dual) pairs of array_like
        ``y``'s real part must be nonzero.

    Returns
    -------
    (real, dual) tuple of arrays
    """
    a, b = x
    c, d = y
    return (np.divide(a, c), np.divide(np.multiply(b, c) - np.multiply(a, d), np.multiply(c, c)))


def apply(f: Callable[[npt.ArrayLike], np.ndarray], df: Callable[[npt.ArrayLike], np.ndarray],
          x: tuple[npt.ArrayLike, npt.ArrayLike]) -> tuple[np.ndarray, np.ndarray]:
    """Extend a real function to dual numbers: ``f(a + eps b) = f(a) + eps b f'(a)`` ([K] eq. 23).

    Parameters
    ----------
    f, df : callable
        The function and its derivative, both applied elementwise to ``x[0]``.
    x : (real, dual) pair of array_like

    Returns
    -------
    (real, dual) tuple of arrays
    """
    a, b = x
    return (f(a), np.multiply(b, df(a)))


def sqrt(x: tuple[npt.ArrayLike, npt.ArrayLike]) -> tuple[np.ndarray, np.ndarray]:
    """Square root ``sqrt(a + eps b) = sqrt(a) + eps b / (2 sqrt(a))`` ([K] eq. 23).

    Parameters
    ----------
    x : (real, dual) pair of array_like
        The real part must be positive.

    Returns
    -------
    (real, dual) tuple of arrays
    """
    a, b = x
    root = np.sqrt(a)
    return (root, np.divide(b, 2 * root))
