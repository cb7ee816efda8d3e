"""One model of free space: where a disc of a given radius may be, past an arena's walls and its
static obstacles (the robots aside).

The scenario loader decides with it that every goal can be reached, and whether the layout is
well-formed: whether each robot can get home past every other robot parked at its goal
(``ground.scenario``).

Free space is sampled on a grid of :data:`REACH_CELLS` cells along the arena's longer side (a 2 m
arena on 5 mm cells): a cell is free when its centre clears every wall and obstacle by the
radius, and free cells that share an edge or a corner are connected.  A passage counts when it
is about a cell wider than twice the radius; one narrower than that never does.  A point belongs
to the piece of free space of the free cell nearest it, if one lies within a cell diagonal.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

REACH_CELLS = 400
"""Cells along the arena's longer side of the free-space grid (a 2 m arena: 5 mm cells)."""


@dataclass(frozen=True)
class Carved:
    """Free space with discs standing in it (:meth:`FreeSpace.carve`)."""

    labels: np.ndarray
    """Piece (nx, ny) of each free cell left, 1 …; 0 where not free."""
    stamps: list[tuple[slice, slice, np.ndarray]]
    """Per disc, the cells it covers (:meth:`FreeSpace.disc_cells`)."""
    discs: list[tuple[np.ndarray, float]]
    """Per disc, its centre (2,) [m] and radius [m]."""


class FreeSpace:
    """The cells (nx, ny) of an arena (xmin, xmax, ymin, ymax) [m] where a disc of ``radius`` [m]
    clears the walls and ``obstacles`` (anything with ``distances(points (M, 2)) -> (M,)`` [m]),
    and the pieces they form (:attr:`labels`)."""

    def __init__(
        self, arena: tuple[float, float, float, float], obstacles: Sequence[Any], radius: float,
        cells: int = REACH_CELLS,
    ) -> None:  # fmt: skip
        from scipy import ndimage

        xmin, xmax, ymin, ymax = arena
        h = max(xmax - xmin, ymax - ymin) / cells
        self.nx, self.ny = max(1, math.ceil((xmax - xmin) / h)), max(1, math.ceil((ymax - ymin) / h))
        self.x0, self.y0 = xmin, ymin
        self.hx, self.hy = (xmax - xmin) / self.nx, (ymax - ymin) / self.ny
        """Cell sides [m]."""
        self.xs = xmin + (np.arange(self.nx) + 0.5) * self.hx
        self.ys = ymin + (np.arange(self.ny) + 0.5) * self.hy
        X, Y = np.meshgrid(self.xs, self.ys, indexing="ij")
        clear = np.minimum(np.minimum(X - xmin, xmax - X), np.minimum(Y - ymin, ymax - Y))
        centres = np.column_stack([X.ravel(), Y.ravel()])
        for obs in obstacles:
            clear = np.minimum(clear, obs.distances(centres).reshape(self.nx, self.ny))
        self.radius = radius
        self.clearance = clear
        """Distance (nx, ny) [m] from each cell's centre to the nearest wall or obstacle."""
        self.free = clear >= radius
        """Cells (nx, ny) whose centre the disc may be at."""
        self.labels, self.pieces = ndimage.label(self.free, structure=np.ones((3, 3), dtype=bool))
        """Piece of free space (nx, ny) of each free cell, 1 … :attr:`pieces`; 0 if not free."""
        self.reach = math.hypot(self.hx, self.hy)
        """A cell's diagonal [m]: how far from a point its free cell may be."""

    def cells(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The indices (ix, iy) of the cells that points P (k, 2) [m] lie in, clipped to the
        grid (each (k,))."""
        P = np.asarray(P, dtype=float).reshape(-1, 2)
        ix = np.clip(((P[:, 0] - self.x0) / self.hx).astype(int), 0, self.nx - 1)
        iy = np.clip(((P[:, 1] - self.y0) / self.hy).astype(int), 0, self.ny - 1)
        return ix, iy

    def piece(self, point: np.ndarray) -> int | None:
        """The piece of free space of a point (2,) [m]: that of the free cell nearest it within a
        cell diagonal; None if no free cell is that near."""
        return self.piece_in(self.labels, point)

    def joined(self, a: np.ndarray, b: np.ndarray) -> bool:
        """Whether the disc can go from point ``a`` to point ``b`` (2,) [m]; a point with no free
        cell near it is not judged here (True)."""
        pa, pb = self.piece(a), self.piece(b)
        return pa is None or pb is None or pa == pb

    def disc_cells(self, centre: np.ndarray, radius: float) -> tuple[slice, slice, np.ndarray]:
        """The cells whose centre lies within ``radius`` [m] of ``centre`` (2,) [m], strictly:
        (rows, columns, mask over that block)."""
        i0 = max(0, int((centre[0] - radius - self.x0) / self.hx))
        i1 = min(self.nx, int((centre[0] + radius - self.x0) / self.hx) + 2)
        j0 = max(0, int((centre[1] - radius - self.y0) / self.hy))
        j1 = min(self.ny, int((centre[1] + radius - self.y0) / self.hy) + 2)
        dx = self.xs[i0:i1, None] - centre[0]
        dy = self.ys[None, j0:j1] - centre[1]
        return slice(i0, i1), slice(j0, j1), dx * dx + dy * dy < radius * radius

    def splits(self, centre: np.ndarray, radius: float, free: np.ndarray | None = None) -> np.ndarray | None:
        """The pieces (nx, ny) free space falls into once a disc of ``radius`` [m] about
        ``centre`` (2,) [m] stands in it too, labelled as :attr:`labels` are; None if the disc
        splits no piece (the ring of free cells just around it is connected).  ``free``: the
        free cells (nx, ny) to split instead of :attr:`free` (with other discs standing in it,
        :meth:`carve`)."""
        from scipy import ndimage

        free = self.free if free is None else free
        if self.ring_holds(centre, radius, free):
            return None  # the free cells about the disc hold together: nothing is split
        rows, cols, m = self.disc_cells(centre, radius)
        free = free.copy()
        free[rows, cols] &= ~m
        out, _ = ndimage.label(free, structure=np.ones((3, 3), dtype=bool))
        return np.asarray(out)

    def ring_holds(self, centre: np.ndarray, radius: float, free: np.ndarray | None = None) -> bool:
        """Whether the free cells just about a disc of ``radius`` [m] about ``centre`` (2,) [m]
        (two cells deep) hold together, in :attr:`free` or the cells ``free`` (nx, ny).  If they
        do, the disc splits no piece of free space, whatever lies beyond them: a way that
        crossed the disc goes round it through them.  Looks at the disc's bounding box only."""
        from scipy import ndimage

        free = self.free if free is None else free
        rows, cols, m = self.disc_cells(centre, radius)
        r0, r1 = max(0, rows.start - 2), min(self.nx, rows.stop + 2)
        c0, c1 = max(0, cols.start - 2), min(self.ny, cols.stop + 2)
        box = free[r0:r1, c0:c1].copy()
        inside = np.zeros_like(box)
        inside[rows.start - r0 : rows.stop - r0, cols.start - c0 : cols.stop - c0] = m
        box &= ~inside
        near = ndimage.binary_dilation(inside, structure=np.ones((3, 3), dtype=bool), iterations=2)
        ring = box & near
        lab, _ = ndimage.label(ring, structure=np.ones((3, 3), dtype=bool))
        return len(np.unique(lab[ring])) <= 1

    def walled_in(self, a: np.ndarray, b: np.ndarray, discs: Sequence[tuple[np.ndarray, float]]) -> list[int]:
        """The discs (centre (2,) [m], radius [m]) that, standing in free space all at once,
        keep the disc from going from ``a`` to ``b`` (2,) [m] that :meth:`joined` joins: those
        that border the piece ``a`` or ``b`` is then shut in (each of the two that is not the
        largest piece left); [] if the way is open."""
        if not self.joined(a, b):
            return []
        return self.walls(self.carve(discs), a, b)

    def carve(self, discs: Sequence[tuple[np.ndarray, float]]) -> Carved:
        """Free space with the discs (centre (2,) [m], radius [m]) standing in it all at once,
        labelled into its pieces: one labelling, for :meth:`walls` to ask of many ways."""
        from scipy import ndimage

        free = self.free.copy()
        stamps = [self.disc_cells(np.asarray(c, dtype=float), r) for c, r in discs]
        for rows, cols, m in stamps:
            free[rows, cols] &= ~m
        lab, _ = ndimage.label(free, structure=np.ones((3, 3), dtype=bool))
        return Carved(np.asarray(lab), stamps, [(np.asarray(c, dtype=float), float(r)) for c, r in discs])

    def walls(self, carved: Carved, a: np.ndarray, b: np.ndarray) -> list[int]:
        """Of the discs ``carved`` (:meth:`carve`), those that keep the way from ``a`` to ``b``
        (2,) [m] shut, as :meth:`walled_in` says; [] if it is open."""
        from scipy import ndimage

        lab = carved.labels
        pa, pb = self.piece_in(lab, a), self.piece_in(lab, b)
        if pa is not None and pa == pb:
            return []
        if pa is None or pb is None:  # a disc covers the point itself
            p = a if pa is None else b
            return [k for k, (c, r) in enumerate(carved.discs) if np.hypot(*(p - c)) < r + self.reach]
        sizes = np.bincount(lab.ravel())
        sizes[0] = 0
        shut = np.isin(lab, [p for p in (pa, pb) if p != int(np.argmax(sizes))])
        rim = ndimage.binary_dilation(shut, structure=np.ones((3, 3), dtype=bool))
        return [k for k, (rows, cols, m) in enumerate(carved.stamps) if np.any(m & rim[rows, cols])]

    def piece_in(self, lab: np.ndarray, p: np.ndarray) -> int | None:
        """The label in ``lab`` of the labelled cell nearest ``p`` (2,) [m] within a cell diagonal."""
        rows, cols, m = self.disc_cells(p, self.reach)
        sub = lab[rows, cols]
        ok = m & (sub > 0)
        if not ok.any():
            return None
        dx = self.xs[rows, None] - p[0]
        dy = self.ys[None, cols] - p[1]
        d = np.where(ok, dx * dx + dy * dy, np.inf)
        return int(sub.ravel()[int(np.argmin(d))])


@functools.lru_cache(maxsize=8)
def _model(arena: tuple[float, float, float, float], obstacles: tuple[Any, ...], radius: float) -> FreeSpace:
    return FreeSpace(arena, obstacles, radius)


def free_space_model(
    arena: tuple[float, float, float, float], obstacles: Sequence[Any], radius: float
) -> FreeSpace:
    """The :class:`FreeSpace` of an arena, its obstacles and a radius [m], made once per process
    and shared (the loader's checks of one scenario all use the same one)."""
    return _model(tuple(float(v) for v in arena), tuple(obstacles), float(radius))  # type: ignore[arg-type]
