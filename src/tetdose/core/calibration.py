"""HU → mass density calibration: a piecewise-linear curve through (HU, g/cm³) nodes.

The paper's eq. (1), ρ_M = a·ρ_H + b, is one segment of it. The default curve is the
Schneider et al. (2000) HU–density table as tabulated by GATE (Schneider2000DensitiesTable):
−1000 HU → 0.00121 g/cm³ … 3000 HU → 2.8 g/cm³. Outside the first and last node the density is
held constant (a CT value below air is noise, not a lower density).

The inverse (density → HU, for virtual CT) needs a rule because the Schneider curve is not
monotonic (1.1199 g/cm³ at 100 HU, 1.0762 at 101 HU): we return the **lowest HU whose forward
density reaches ρ**, ``HU(ρ) = min{h : f(h) ≥ ρ}``. Then ``f(HU(ρ)) = ρ`` for every ρ in range,
and ``HU(f(h)) = h`` wherever the curve is increasing and not overtaken by an earlier part of it
(for the default table: every HU except 101…~175, which map back onto 23…100).

**Beyond the table.** :meth:`HUCalibration.range_report` counts the voxels below the first and
above the last node and what they became; :meth:`HUCalibration.density_checked` warns
(``warnings.warn``) when any lies above the last node — a metal implant (titanium ≈ 4.5 g/cm³,
steel ≈ 8 g/cm³, thousands of HU beyond 3000) would silently become the last node's bone. Values
below the first node (air padding such as −1024 or −3024 HU) become air and are only counted.
"""

from __future__ import annotations

import csv
import os
import warnings
from dataclasses import asdict, dataclass

import numpy as np

from tetdose._typing import FloatArray
from tetdose.errors import CalibrationError

#: Densest material [g/cm³] (osmium 22.59) rounded up: larger densities are in other units.
MAX_DENSITY_G_CM3 = 23.0
#: Schneider 2000 nodes (HU, g/cm³), as tabulated by GATE.
SCHNEIDER_2000 = (
    (-1000.0, 0.00121),
    (-98.0, 0.93),
    (-97.0, 0.930486),
    (14.0, 1.03),
    (23.0, 1.031),
    (100.0, 1.1199),
    (101.0, 1.0762),
    (1600.0, 1.9642),
    (3000.0, 2.8),
)


@dataclass(frozen=True)
class RangeReport:
    """Voxels beyond a calibration's table: counts, extreme HU, and the densities they got."""

    calibration: str
    table_hu: tuple[float, float]
    n_below: int
    n_above: int
    lowest_hu: float
    highest_hu: float
    density_below_g_cm3: float
    density_above_g_cm3: float

    def as_dict(self) -> dict[str, object]:
        return asdict(self)

    def message(self, what: str) -> str:
        """One line for a warning about the voxels above the table."""
        return (f"{what}: {self.n_above} voxels lie above the calibration's last node "
                f"({self.table_hu[1]:g} HU, up to {self.highest_hu:g} HU) and became "
                f"{self.density_above_g_cm3:g} g/cm³ of the density-class material ({self.n_below} "
                f"below {self.table_hu[0]:g} HU became {self.density_below_g_cm3:g} g/cm³); metal "
                "is neither: give --calibration a CSV extending the table to the insert's HU with "
                "its density (titanium ≈ 4.5, steel ≈ 8 g/cm³), or mask the artefact")


@dataclass(frozen=True, eq=False)
class HUCalibration:
    """Piecewise-linear HU → density [g/cm³] curve through ``(hu, density_g_cm3)`` nodes.

    Parameters
    ----------
    hu : (N,) float
        CT numbers of the nodes [HU], strictly increasing, N ≥ 2.
    density_g_cm3 : (N,) float
        Mass density at each node [g/cm³], ≥ 0; held constant beyond the end nodes.
    name : str
        Recorded in the outputs (``"schneider2000"`` for the default curve).

    Raises
    ------
    CalibrationError
        Fewer than two nodes, non-finite values, HU not increasing, or a negative density.

    Examples
    --------
    >>> cal = HUCalibration([-1000.0, 0.0, 1000.0], [0.0, 1.0, 2.0])
    >>> cal.density([-500.0, 500.0]).tolist()
    [0.5, 1.5]
    >>> float(cal.hu_of(1.5))                     # the inverse, for a virtual CT
    500.0
    >>> HUCalibration.schneider2000().density([100.0, 101.0]).tolist()  # not monotonic
    [1.1199, 1.0762]
    """

    hu: FloatArray
    density_g_cm3: FloatArray
    name: str = "custom"

    def __post_init__(self) -> None:
        hu = np.asarray(self.hu, dtype=np.float64).reshape(-1)
        rho = np.asarray(self.density_g_cm3, dtype=np.float64).reshape(-1)
        if len(hu) != len(rho) or len(hu) < 2:
            raise CalibrationError("a calibration needs at least two (HU, density) nodes")
        if not (np.all(np.isfinite(hu)) and np.all(np.isfinite(rho))):
            raise CalibrationError("calibration nodes must be finite numbers")
        if np.any(np.diff(hu) <= 0):
            i = int(np.flatnonzero(np.diff(hu) <= 0)[0])
            raise CalibrationError(
                f"calibration HU values must be strictly increasing (row {i + 2}: {hu[i + 1]:g} "
                f"after {hu[i]:g}); sort the table and remove duplicate HU"
            )
        if np.any(rho < 0):
            raise CalibrationError("calibration densities must be non-negative")
        object.__setattr__(self, "hu", hu)
        object.__setattr__(self, "density_g_cm3", rho)
        object.__setattr__(self, "_inverse", _inverse_pieces(hu, rho))

    @classmethod
    def schneider2000(cls) -> HUCalibration:
        """The default curve: Schneider et al. 2000 (Phys. Med. Biol. 45:459), GATE's table."""
        nodes = np.array(SCHNEIDER_2000)
        return cls(nodes[:, 0], nodes[:, 1], name="schneider2000")

    @classmethod
    def linear(cls, slope: float, intercept: float, hu_range: tuple[float, float] = (-1000, 3000)
               ) -> HUCalibration:
        """One segment, the paper's eq. (1): ρ = slope·HU + intercept."""
        hu = np.array(hu_range, dtype=np.float64)
        return cls(hu, slope * hu + intercept, name=f"linear({slope:g}, {intercept:g})")

    @classmethod
    def from_csv(cls, path: str | os.PathLike[str]) -> HUCalibration:
        """Read nodes from a CSV: two columns (HU, density in g/cm³); a header line is allowed."""
        rows: list[tuple[float, float]] = []
        try:
            with open(path, newline="") as f:
                for line_no, row in enumerate(csv.reader(f), start=1):
                    cells = [c.strip() for c in row if c.strip()]
                    if not cells or cells[0].startswith("#"):
                        continue
                    try:
                        rows.append((float(cells[0]), float(cells[1])))
                    except (ValueError, IndexError):
                        if rows:
                            raise CalibrationError(
                                f"{path}:{line_no}: expected two numbers (HU, g/cm³), got {row}"
                            ) from None
        except OSError as exc:
            raise CalibrationError(f"cannot read calibration {path}: {exc.strerror}") from exc
        if not rows:
            raise CalibrationError(f"{path} holds no (HU, density) rows")
        arr = np.array(rows)
        if arr[:, 1].max() > MAX_DENSITY_G_CM3:
            raise CalibrationError(
                f"{path}: densities reach {arr[:, 1].max():g}, denser than any material (osmium "
                "22.6 g/cm³): kg/m³ or HU in the density column? give g/cm³ (water 1.0)")
        return cls(arr[:, 0], arr[:, 1], name=os.fspath(path))

    def density(self, hu: np.ndarray | float) -> np.ndarray:
        """Density [g/cm³] for CT numbers [HU] (held constant beyond the end nodes)."""
        return np.interp(np.asarray(hu, dtype=np.float64), self.hu, self.density_g_cm3)

    __call__ = density

    def range_report(self, hu: np.ndarray) -> RangeReport:
        """How many values of ``hu`` lie below the first / above the last node."""
        a = np.asarray(hu)
        lo, hi = self.hu[0], self.hu[-1]
        return RangeReport(self.name, (float(lo), float(hi)), int(np.count_nonzero(a < lo)),
                           int(np.count_nonzero(a > hi)), float(a.min()) if a.size else lo,
                           float(a.max()) if a.size else hi, float(self.density_g_cm3[0]),
                           float(self.density_g_cm3[-1]))

    def density_checked(self, hu: np.ndarray, what: str = "the CT"
                        ) -> tuple[np.ndarray, RangeReport]:
        """:meth:`density` and the :class:`RangeReport`, warning when voxels lie above the table
        (see the module docstring)."""
        report = self.range_report(hu)
        if report.n_above:
            warnings.warn(report.message(what), stacklevel=2)
        return self.density(hu), report

    def hu_of(self, density_g_cm3: np.ndarray | float) -> np.ndarray:
        """Inverse: the lowest HU whose density reaches ``density_g_cm3`` (see module doc)."""
        lo, hi, h_lo, h_hi = self._inverse  # type: ignore[attr-defined]
        rho = np.clip(np.asarray(density_g_cm3, dtype=np.float64), lo[0], hi[-1])
        p = np.minimum(np.searchsorted(hi, rho, side="left"), len(hi) - 1)
        span = hi[p] - lo[p]
        t = np.divide(rho - lo[p], span, out=np.zeros_like(rho), where=span > 0)
        return h_lo[p] + t * (h_hi[p] - h_lo[p])


def _inverse_pieces(hu: FloatArray, rho: FloatArray) -> tuple[FloatArray, ...]:
    """Pieces (ρ_lo, ρ_hi, HU_lo, HU_hi) of ``HU(ρ) = min{h : f(h) ≥ ρ}`` for a continuous f."""
    lo, hi, h_lo, h_hi = [rho[0]], [rho[0]], [hu[0]], [hu[0]]
    running = rho[0]
    for a in range(len(hu) - 1):
        d0, d1, g0, g1 = rho[a], rho[a + 1], hu[a], hu[a + 1]
        if d1 <= running:
            continue
        start = g0 if d0 >= running else g0 + (running - d0) / (d1 - d0) * (g1 - g0)
        lo.append(running)
        hi.append(d1)
        h_lo.append(start)
        h_hi.append(g1)
        running = d1
    return tuple(np.array(v) for v in (lo, hi, h_lo, h_hi))
