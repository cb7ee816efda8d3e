"""Zonotopes, support functions and mRPI outer approximations.

A zonotope is ``Z = {c + G λ : ‖λ‖∞ ≤ 1}`` with centre ``c`` (n,) and
generators ``G`` (n, m).  Its support function is
``h_Z(d) = dᵀc + Σ_i |dᵀ G_i|``, which gives every constraint tightening
without vertex enumeration (docs/method.md §3).

The mRPI outer approximation follows Raković et al. (2005), "Invariant
approximations of the minimal robust positively invariant set", IEEE TAC:
for ``z⁺ = A z + w``, ``w ∈ W`` (a zonotope centred at 0), pick ``s`` and
``α`` with ``A^s W ⊆ α W``; then ``F(α, s) = (1 − α)⁻¹ ⊕_{i<s} A^i W`` is RPI
and ``F_∞ ⊆ F(α, s) ⊆ F_∞ ⊕ B_∞(err)`` with the a-priori bound
``err = α/(1 − α) · max_j h_{F_s}(±e_j)``.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


class SetComputationError(RuntimeError):
    """An offline set computation did not converge within its iteration cap."""


@dataclass(frozen=True)
class Zonotope:
    """``{c + G λ : ‖λ‖∞ ≤ 1}``; ``c`` has shape (n,), ``G`` shape (n, m)."""

    c: Array
    G: Array

    @staticmethod
    def box(half_widths: Array) -> Zonotope:
        """Axis-aligned box centred at 0 with the given half-widths (n,)."""
        hw = np.asarray(half_widths, dtype=float)
        keep = hw > 0
        return Zonotope(np.zeros(hw.size), np.diag(hw)[:, keep])

    @property
    def dim(self) -> int:
        """Dimension n of the space (the size of ``c``)."""
        return int(self.c.size)

    def support(self, d: Array) -> Array:
        """Support function h_Z(d) = max_{z∈Z} dᵀz.

        ``d`` is a direction (n,) or a stack of directions (k, n); the result is
        a scalar array or shape (k,)."""
        d = np.asarray(d, dtype=float)
        return d @ self.c + np.abs(d @ self.G).sum(axis=-1)

    def interval_hull(self) -> Array:
        """Half-widths of the bounding box around the centre, shape (n,)."""
        return np.abs(self.G).sum(axis=1)

    def linear_map(self, M: Array) -> Zonotope:
        """The image ``M Z``; ``M`` has shape (k, n)."""
        M = np.atleast_2d(np.asarray(M, dtype=float))
        return Zonotope(M @ self.c, M @ self.G)

    def minkowski_sum(self, other: Zonotope) -> Zonotope:
        """``Z ⊕ other``."""
        return Zonotope(self.c + other.c, np.hstack([self.G, other.G]))

    def scale(self, factor: float) -> Zonotope:
        """The image ``factor · Z``: centre and generators scaled (about the origin, not the centre)."""
        return Zonotope(self.c * factor, self.G * factor)

    def halfspaces(self, tol: float = 1e-12) -> tuple[Array, Array]:
        """Exact H-representation ``{z : |F (z − c)| ≤ f}`` as (F, f).

        Each facet pair of a zonotope is normal to n − 1 linearly independent
        generators; every such normal is a candidate and the non-facets are
        redundant but harmless.  Normals are unit length; duplicates (up to
        sign) are merged.  Returns F (p, n) and f (p,)."""
        n = self.dim
        G = self.G[:, np.linalg.norm(self.G, axis=0) > tol]
        if G.shape[1] < n:
            raise SetComputationError(
                f"zonotope is degenerate: {G.shape[1]} generators span fewer than {n} dimensions"
            )
        normals: list[Array] = []
        if n == 1:
            normals = [np.ones(1)]
        elif n == 2:
            normals = [np.array([-g[1], g[0]]) for g in G.T]
        else:
            for cols in itertools.combinations(range(G.shape[1]), n - 1):
                sub = G[:, cols]
                # The normal is the null vector of subᵀ.
                _, sv, vt = np.linalg.svd(sub.T)
                if sv[-1] < tol * max(1.0, sv[0]):
                    continue
                normals.append(vt[-1])
        F = np.array(normals, dtype=float)
        F /= np.linalg.norm(F, axis=1, keepdims=True)
        # Canonical sign: first significant entry positive, then dedupe.
        idx = np.argmax(np.abs(F) > 1e-9, axis=1)
        F *= np.sign(F[np.arange(F.shape[0]), idx])[:, None]
        F = np.unique(np.round(F, 12), axis=0)
        F /= np.linalg.norm(F, axis=1, keepdims=True)
        f = np.abs(F @ G).sum(axis=1)
        return F, f

    def contains(self, z: Array, tol: float = 1e-9) -> bool:
        """Membership by the exact H-representation."""
        F, f = self.halfspaces()
        return bool(np.all(np.abs(F @ (np.asarray(z) - self.c)) <= f + tol))


def unit_directions(n: int, count: int, seed: int = 0) -> Array:
    """``count`` unit directions in R^n, shape (count, n).

    In 2-D they are evenly spaced; otherwise the ± coordinate axes followed by
    seeded random directions."""
    if n == 2:
        ang = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
        return np.column_stack([np.cos(ang), np.sin(ang)])
    eye = np.vstack([np.eye(n), -np.eye(n)])
    rng = np.random.default_rng(seed)
    extra = rng.standard_normal((max(count - 2 * n, 0), n))
    d = np.vstack([eye, extra])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@dataclass(frozen=True)
class MRPIApprox:
    """Result of :func:`mrpi_outer`."""

    Z: Zonotope
    """The RPI outer approximation F(α, s)."""
    alpha: float
    s: int
    error_bound: float
    """A-priori bound: F(α, s) ⊆ F_∞ ⊕ B_∞(error_bound)."""


def mrpi_outer(A: Array, W: Zonotope, tol: float, max_terms: int) -> MRPIApprox:
    """Outer ε-approximation of the mRPI set of ``z⁺ = A z + w``, ``w ∈ W``.

    ``A`` (n, n) must be Schur; ``W`` a full-dimensional zonotope centred at
    the origin.  Terms are added
    until the a-priori error bound is below ``tol``; if that needs more than
    ``max_terms`` terms, :class:`SetComputationError` is raised.
    """
    A = np.asarray(A, dtype=float)
    rho = max(abs(np.linalg.eigvals(A)))
    if rho >= 1.0:
        raise SetComputationError(f"A is not Schur (spectral radius {rho:.4f} ≥ 1)")
    n = A.shape[0]
    if not np.allclose(W.c, 0.0):
        raise SetComputationError("W must be centred at the origin")
    if W.G.shape[1] < n or np.linalg.matrix_rank(W.G) < n:
        raise SetComputationError("W must be full-dimensional (pad zero half-widths)")
    gens = [W.G]
    Ai = np.eye(n)
    # α(s) = min{α : A^s W ⊆ α W} = max_j h_{A^s W}(F_j) / f_j over W's facets
    # (Raković 2005, eq. 11).
    F, f = W.halfspaces()
    for s in range(1, max_terms + 1):
        Ai = A @ Ai
        alpha = float(np.max(np.abs(F @ Ai @ W.G).sum(axis=1) / f))
        if alpha < 1.0:
            Fs = Zonotope(np.zeros(n), np.hstack(gens))
            err = alpha / (1.0 - alpha) * float(np.max(Fs.interval_hull()))
            if err <= tol:
                return MRPIApprox(Fs.scale(1.0 / (1.0 - alpha)), alpha, s, err)
        gens.append(Ai @ W.G)
    raise SetComputationError(
        f"mRPI approximation did not reach error {tol:g} within {max_terms} terms "
        f"(spectral radius {rho:.4f}); raise mrpi_max_terms or mrpi_tol"
    )
