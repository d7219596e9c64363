"""Topological sliver repair: edge removal (3-2, 4-4, n→2n−4 flips), 2-3 flips and the
reassignment of surface tetrahedra, each confined to one region so that no boundary or
interface face changes (except where a whole tetrahedron changes side, see 3).

Quality q of a tetrahedron = its smallest dihedral angle [°] (−∞ if it is not positively
oriented). A bad tetrahedron t (q < threshold) is treated by the best of these local moves
(Klingner & Shewchuk, "Aggressive tetrahedral mesh improvement", Proc. 16th Int. Meshing
Roundtable (2007) 3–23; Freitag & Ollivier-Gooch, IJNME 40 (1997) 3979–4002), each accepted
only when the smallest q of the new tetrahedra exceeds the smallest q of the ones they replace
(the sorted quality vector rises, so the sequence terminates):

1. **Edge removal** of an edge of t whose ring of tetrahedra is closed and lies in one region
   (the edge and all faces through it are interior to that region): the ring polygon
   r_0 … r_{n−1} (ordered so that (a, b, r_i, r_{i+1}) is positive) is retriangulated by the
   triangulation maximising the smallest q of the tetrahedra (a, r_i, r_k, r_j) and
   (b, r_i, r_j, r_k), i < k < j, found by dynamic programming over sub-polygons in O(n³)
   (Shewchuk, "Two discrete optimization algorithms for the topological improvement of
   tetrahedral meshes", 2002). n = 3 is the 3-2 flip, n = 4 the 4-4 flip. The ring's outer
   faces are kept, so every boundary and interface face stays.
2. **2-3 flip** of a face of t shared with a tetrahedron of the same region: (a, b, c, d) and
   (a, b, c, e) become (d, e, a, b), (d, e, b, c), (d, e, c, a); the six outer faces stay.
3. **Reassignment** of t when at least two of its faces lie on the surface towards the same
   side X (the outer boundary, or the region X across an interface): t moves to X (is deleted
   when X is the outside). This is done only for flat tetrahedra (smallest altitude ≤
   ``FLAT_FRACTION`` × mean edge), so the surface moves by less than that altitude and the
   volumes by the sliver's (≪ 1 mm³), and only when the edge that becomes a surface edge has
   no other tetrahedron of X around it (no pinched surface).
   A flip reaching the threshold is preferred; reassignment comes next; otherwise the best
   improving flip is taken. A flip that would add an edge or a face the mesh already has
   outside the tetrahedra it replaces is never taken (its retriangulation would overlap them).
"""

from __future__ import annotations

from itertools import combinations

import numpy as np

from tetdose._typing import FloatArray, IntArray
from tetdose.core.mesh import FACE_VERTICES
from tetdose.meshing._relocation_kernels import min_dihedral_vol6

#: Largest ring of tetrahedra around an edge considered for edge removal.
MAX_RING = 12
#: A move must raise the smallest dihedral angle of the tetrahedra it replaces by this [°].
MIN_GAIN_DEG = 1e-6
#: Only tetrahedra whose smallest altitude is at most this fraction of their mean edge change
#: side (move 3): flat ones, so that the surface moves by less than that altitude.
FLAT_FRACTION = 0.15
#: Region value for "outside the mesh".
OUTSIDE = -1
#: The six edges (i, j) of a tetrahedron by local vertex index.
_EDGE_PAIRS = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))


def tet_quality(points_mm: FloatArray, tets: IntArray) -> FloatArray:
    """Smallest dihedral angle [°] of each tetrahedron; −∞ where its signed volume ≤ 0."""
    angle, vol6 = min_dihedral_vol6(points_mm, np.asarray(tets, dtype=np.intp).reshape(-1, 4))
    return np.where(vol6 > 0.0, angle, -np.inf)


def _even(perm: tuple[int, ...]) -> bool:
    """Whether the permutation ``perm`` of 0…3 is even (counted inversions)."""
    return sum(perm[i] > perm[j] for i in range(4) for j in range(i + 1, 4)) % 2 == 0


class _Mesh:
    """Tetrahedra with lazily built vertex stars (sets of tet ids), for local edits."""

    def __init__(self, points_mm: FloatArray, tets: IntArray, region: IntArray) -> None:
        m = len(tets)
        self.points = points_mm
        self.tets = np.empty((m + 1024, 4), dtype=np.intp)
        self.tets[:m] = tets
        self.region = np.empty(m + 1024, dtype=np.int64)
        self.region[:m] = region
        self.alive = np.zeros(m + 1024, dtype=bool)
        self.alive[:m] = True
        self.n = m
        flat = np.asarray(tets).ravel()
        order = np.argsort(flat, kind="stable")
        self._offsets = np.zeros(len(points_mm) + 1, dtype=np.intp)
        np.cumsum(np.bincount(flat, minlength=len(points_mm)), out=self._offsets[1:])
        self._star_tets = order // 4
        self._stars: dict[int, set[int]] = {}

    def star(self, v: int) -> set[int]:
        """Ids of the live tetrahedra around vertex ``v`` (built on first use, then kept)."""
        s = self._stars.get(v)
        if s is None:
            s = set(self._star_tets[self._offsets[v]:self._offsets[v + 1]].tolist())
            self._stars[v] = s
        return s

    def quality(self, ids: list[int]) -> FloatArray:
        return tet_quality(self.points, self.tets[ids])

    def kill(self, ids: list[int]) -> None:
        for t in ids:
            for v in self.tets[t].tolist():
                self.star(v).discard(t)
            self.alive[t] = False

    def add(self, new: IntArray, region: int) -> list[int]:
        k = len(new)
        if self.n + k > len(self.tets):
            grow = max(k, len(self.tets) // 2)
            self.tets = np.concatenate([self.tets, np.empty((grow, 4), dtype=np.intp)])
            self.region = np.concatenate([self.region, np.empty(grow, dtype=np.int64)])
            self.alive = np.concatenate([self.alive, np.zeros(grow, dtype=bool)])
        ids = list(range(self.n, self.n + k))
        self.tets[self.n:self.n + k] = new
        self.region[self.n:self.n + k] = region
        self.alive[self.n:self.n + k] = True
        self.n += k
        for t in ids:
            for v in self.tets[t].tolist():
                self.star(v).add(t)
        return ids

    def ring(self, a: int, b: int) -> tuple[list[int], list[int]] | None:
        """(ring vertices in order with (a, b, r_i, r_{i+1}) positive, tet ids) of edge (a, b),
        or None when the ring is open or spans more than one region."""
        ids = sorted(self.star(a) & self.star(b))
        if len(ids) < 3 or len(ids) > MAX_RING or len(set(self.region[ids].tolist())) != 1:
            return None
        nxt: dict[int, int] = {}
        for t in ids:
            row = self.tets[t].tolist()
            ia, ib = row.index(a), row.index(b)
            k, l = (i for i in range(4) if i not in (ia, ib))
            x, y = (row[k], row[l]) if _even((ia, ib, k, l)) else (row[l], row[k])
            if x in nxt:
                return None
            nxt[x] = y
        start = next(iter(nxt))
        ring = [start]
        while len(ring) <= len(ids):
            v = nxt.get(ring[-1])
            if v is None:
                return None
            if v == start:
                break
            ring.append(v)
        return (ring, ids) if len(ring) == len(ids) and nxt.get(ring[-1]) == start else None

    def closed(self, a: int, b: int) -> bool:
        """Whether every face through edge (a, b) has two tetrahedra (the edge is not on the
        outer boundary), whatever their regions."""
        count: dict[int, int] = {}
        for t in self.star(a) & self.star(b):
            for v in self.tets[t].tolist():
                if v != a and v != b:
                    count[v] = count.get(v, 0) + 1
        return bool(count) and all(c == 2 for c in count.values())

    def neighbour(self, t: int, f: int) -> int:
        """Tet across face ``f`` (opposite local vertex f) of tet ``t``, or −1."""
        a, b, c = self.tets[t, FACE_VERTICES[f]].tolist()
        other = (self.star(a) & self.star(b) & self.star(c)) - {t}
        return other.pop() if other else -1


def _fresh(mesh: _Mesh, old: list[int], new: IntArray) -> bool:
    """Whether replacing the tets ``old`` by ``new`` adds no edge or face that the mesh already
    has outside ``old`` (the precondition of every flip: else a face would get three tets)."""
    rows = [mesh.tets[t].tolist() for t in old]
    old_edges = {frozenset(e) for r in rows for e in combinations(r, 2)}
    old_faces = {frozenset(f) for r in rows for f in combinations(r, 3)}
    outside = set(old)
    for tet in new.tolist():
        for e in combinations(tet, 2):
            if frozenset(e) not in old_edges and (mesh.star(e[0]) & mesh.star(e[1])) - outside:
                return False
        for f in combinations(tet, 3):
            if frozenset(f) not in old_faces and (
                    mesh.star(f[0]) & mesh.star(f[1]) & mesh.star(f[2])) - outside:
                return False
    return True


def _edge_removal(mesh: _Mesh, a: int, b: int, ring: list[int]) -> tuple[float, IntArray]:
    """Best retriangulation of the ring of edge (a, b) (module doc, 1): (its smallest q, tets)."""
    n = len(ring)
    triples = [(i, k, j) for i in range(n) for j in range(i + 2, n) for k in range(i + 1, j)]
    tri = np.asarray(triples)
    r = np.asarray(ring)[tri]
    tets = np.concatenate([np.column_stack([np.full(len(r), a), r[:, 0], r[:, 1], r[:, 2]]),
                           np.column_stack([np.full(len(r), b), r[:, 0], r[:, 2], r[:, 1]])])
    q = tet_quality(mesh.points, tets)
    qt = dict(zip(triples, np.minimum(q[:len(r)], q[len(r):]).tolist(), strict=True))
    best: dict[tuple[int, int], float] = {(i, i + 1): np.inf for i in range(n - 1)}
    split: dict[tuple[int, int], int] = {}
    for length in range(2, n):
        for i in range(n - length):
            j = i + length
            value, arg = -np.inf, i + 1
            for k in range(i + 1, j):
                v = min(best[i, k], best[k, j], qt[i, k, j])
                if v > value:
                    value, arg = v, k
            best[i, j], split[i, j] = value, arg
    out = []
    stack = [(0, n - 1)]
    while stack:
        i, j = stack.pop()
        if j - i < 2:
            continue
        k = split[i, j]
        out += [(a, ring[i], ring[k], ring[j]), (b, ring[i], ring[j], ring[k])]
        stack += [(i, k), (k, j)]
    return best[0, n - 1], np.asarray(out, dtype=np.intp)


def _flat(points_mm: FloatArray, tet: IntArray) -> bool:
    """Whether the tetrahedron's smallest altitude 3V / max face area is at most
    ``FLAT_FRACTION`` × its mean edge (a sliver or cap, not merely a badly shaped one)."""
    p = points_mm[tet]
    area = max(float(np.linalg.norm(np.cross(*(p[FACE_VERTICES[f][1:]] - p[FACE_VERTICES[f][0]]))))
               for f in range(4)) / 2.0
    volume = abs(float(np.dot(p[1] - p[0], np.cross(p[2] - p[0], p[3] - p[0])))) / 6.0
    edge = np.mean([np.linalg.norm(p[j] - p[i]) for i, j in _EDGE_PAIRS])
    return 3.0 * volume / max(area, 1e-300) <= FLAT_FRACTION * edge


def _reassignment(mesh: _Mesh, t: int) -> int | None:
    """Region t may move to (module doc, 3: ``OUTSIDE`` = delete), or None."""
    if not _flat(mesh.points, mesh.tets[t]):
        return None
    sides = [mesh.neighbour(t, f) for f in range(4)]
    own = int(mesh.region[t])
    side_region = [OUTSIDE if u < 0 else int(mesh.region[u]) for u in sides]
    counts: dict[int, list[int]] = {}
    for f, x in enumerate(side_region):
        if x != own:
            counts.setdefault(x, []).append(f)
    for x, faces in sorted(counts.items(), key=lambda kv: (-len(kv[1]), kv[0])):
        if len(faces) < 2:
            return None
        if len(faces) == 2:  # the edge joining the two other vertices becomes a surface edge
            i, j = faces
            a, b = int(mesh.tets[t, i]), int(mesh.tets[t, j])
            around = (mesh.star(a) & mesh.star(b)) - {t}
            if x == OUTSIDE:
                if not mesh.closed(a, b):  # already on the boundary: a pinched surface
                    return None
            elif any(int(mesh.region[u]) == x for u in around):
                return None
        return x
    return None


def flipped(points_mm: FloatArray, tets: IntArray, region: IntArray, min_dihedral_deg: float,
            bad: IntArray | None = None) -> tuple[IntArray, IntArray, IntArray]:
    """(tets, region, ids of the tets still bad) after the moves of the module doc on every
    tetrahedron with a dihedral angle below ``min_dihedral_deg`` [°] (``bad``: their ids, if
    known); points unchanged (some may become unused)."""
    mesh = _Mesh(points_mm, np.asarray(tets, dtype=np.intp), np.asarray(region, dtype=np.int64))
    if bad is None:
        bad = np.flatnonzero(tet_quality(points_mm, tets) < min_dihedral_deg)
    queue = np.asarray(bad).tolist()
    budget = 20 * len(queue) + 100
    moved: set[int] = set()  # reassigned once: not back again (no ping-pong)
    head = 0
    while head < len(queue) and budget > 0:
        t = queue[head]
        head += 1
        if not mesh.alive[t]:
            continue
        q_t = float(mesh.quality([t])[0])
        if q_t >= min_dihedral_deg:
            continue
        budget -= 1
        best = (-np.inf, None, None, 0)  # (gain-ranked q_new, old ids, new tets, region)
        row = mesh.tets[t].tolist()
        for i, j in _EDGE_PAIRS:
            ring = mesh.ring(row[i], row[j])
            if ring is None:
                continue
            q_old = float(mesh.quality(ring[1]).min())
            q_new, new = _edge_removal(mesh, row[i], row[j], ring[0])
            if q_new > q_old + MIN_GAIN_DEG and q_new > best[0] and _fresh(mesh, ring[1], new):
                best = (q_new, ring[1], new, int(mesh.region[t]))
        for f in range(4):
            u = mesh.neighbour(t, f)
            if u < 0 or mesh.region[u] != mesh.region[t]:
                continue
            a, b, c = mesh.tets[t, FACE_VERTICES[f]].tolist()
            d = row[f]
            e = next(v for v in mesh.tets[u].tolist() if v not in (a, b, c))
            new = np.array([(d, e, a, b), (d, e, b, c), (d, e, c, a)], dtype=np.intp)
            q_new = float(tet_quality(points_mm, new).min())
            q_old = min(q_t, float(mesh.quality([u])[0]))
            if q_new > q_old + MIN_GAIN_DEG and q_new > best[0] and _fresh(mesh, [t, u], new):
                best = (q_new, [t, u], new, int(mesh.region[t]))
        if best[0] < min_dihedral_deg and t not in moved:
            x = _reassignment(mesh, t)
            if x is not None:
                if x == OUTSIDE:
                    mesh.kill([t])
                else:  # now interior to X on two faces: flips there may remove it
                    mesh.region[t] = x
                    moved.add(t)
                    queue.append(t)
                continue
        if best[1] is None:
            continue
        mesh.kill(best[1])
        ids = mesh.add(best[2], best[3])
        q = mesh.quality(ids)
        queue += [i for i, qi in zip(ids, q.tolist(), strict=True) if qi < min_dihedral_deg]
    keep = mesh.alive[:mesh.n]
    new_id = np.cumsum(keep) - 1
    left = np.unique([t for t in queue if mesh.alive[t]]).astype(np.intp)
    left = left[mesh.quality(left.tolist()) < min_dihedral_deg] if left.size else left
    return mesh.tets[:mesh.n][keep].copy(), mesh.region[:mesh.n][keep].copy(), new_id[left]
