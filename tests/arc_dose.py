"""Dose of linac deliveries on a water cylinder (voxel engine), for the arc and sliding-window
tests: an arc against the sum of its static beams, a sliding window against step-and-shoot of its
interpolated apertures. The cylinder's axis is the patient's head–foot axis (z), the gantry's
rotation axis for HFS at couch 0."""

import numpy as np

from tetdose.compare.gamma import gamma_index
from tetdose.core.image import Image, ImageGrid
from tetdose.plan import Plan
from tetdose.transport import TransportSettings, simulate


def water_cylinder(radius_mm=100.0, voxel_mm=5.0, n_xy=44, n_z=4):
    """(density, labels): a water cylinder of ``radius_mm`` about z in an air-free grid (the
    voxels outside are vacuum), centred on the isocentre (0, 0, 0)."""
    origin = np.array([-(n_xy - 1) / 2, -(n_xy - 1) / 2, -(n_z - 1) / 2]) * voxel_mm
    grid = ImageGrid(origin, np.full(3, voxel_mm), np.eye(3), (n_xy, n_xy, n_z))
    k, j, i = np.indices(grid.shape)
    x, y = origin[0] + i * voxel_mm, origin[1] + j * voxel_mm
    rho = (x**2 + y**2 <= radius_mm**2).astype(float)
    return Image(rho, grid), Image(np.ones(grid.shape, dtype=np.int16), grid)


def dose(beams, n, seed, geometry, batches=20):
    """(dose, σ) [per source photon] of linac ``beams`` (plan.toml tables) on ``geometry``."""
    rho, lab = geometry
    plan = Plan.from_dict({"beam": beams, "materials": {1: "water"}})
    r = simulate(rho, plan, TransportSettings(n, batches, seed, physics="kerma"), labels=lab, progress=False)
    return r.dose_gy.reshape(rho.grid.shape), r.dose_std_gy.reshape(rho.grid.shape)


def linac(**kw):
    return {"type": "linac", "spectrum": "6MV", "isocenter_mm": [0, 0, 0], **kw}


def statics(start_deg, stop_deg, step_deg, mu, **kw):
    """Static beams every ``step_deg`` from start to stop (inclusive) sharing ``mu`` by the
    trapezoidal rule (the two end beams half): the quadrature of the arc start → stop. (Equal
    weights would be the arc from start − step/2 to stop + step/2, 1 % wider for 91 beams over
    180°, and 1 % less dose per degree: a difference the full-size test resolves.)"""
    angles = np.arange(start_deg, stop_deg + step_deg / 2, step_deg)
    w = np.ones(len(angles))
    w[[0, -1]] = 0.5
    return [linac(gantry_deg=float(g), weight=mu * wi / w.sum(), **kw)
            for g, wi in zip(angles, w, strict=True)]


def compare(a, b, threshold=0.2):
    """(fraction of voxels within 3σ, mean z², n) over voxels above ``threshold`` × max of
    ``a``; a and b are (dose, σ) with the same normalization, z = (a − b)/sqrt(σa² + σb²).
    With σ from B batches each, z follows Student's t with about 2(B − 1) degrees of freedom:
    E[z²] = ν/(ν − 2) ≈ 1.06 for B = 20, and 99.5 % of |z| < 3."""
    (da, sa), (db, sb) = a, b
    sel = da > threshold * da.max()
    z = (da - db)[sel] / np.sqrt(sa**2 + sb**2)[sel]
    return float(np.mean(np.abs(z) < 3)), float(np.mean(z**2)), int(sel.sum())


def gamma_pass(a, b, grid, dose_percent=2.0, dta_mm=2.0):
    """Global γ pass rate [%] of b against a (threshold 10 %)."""
    return gamma_index(Image(a, grid), Image(b, grid), dose_percent=dose_percent,
                       dta_mm=dta_mm).pass_rate_percent


def sliding_window(k_steps=None, gap_mm=10.0, start_mm=-40.0, stop_mm=30.0, mu=100.0):
    """A leaf gap of ``gap_mm`` sweeping from ``start_mm`` to ``stop_mm`` (bank-1 edge) under
    8 leaf pairs of 5 mm, gantry 0: one sliding-window segment (``k_steps`` None), or
    step-and-shoot of its apertures interpolated at the middles of ``k_steps`` equal parts."""
    bnd = [-20.0 + 5.0 * i for i in range(9)]

    def leaves(edge):
        return [edge] * 8 + [edge + gap_mm] * 8

    if k_steps is None:
        cps = [{"meterset_weight": 0.0, "mlc": leaves(start_mm)},
               {"meterset_weight": 1.0, "mlc": leaves(stop_mm)}]
    else:
        cps = []
        for k in range(k_steps):
            edge = start_mm + (k + 0.5) / k_steps * (stop_mm - start_mm)
            cps += [{"meterset_weight": k / k_steps, "mlc": leaves(edge)},
                    {"meterset_weight": (k + 1) / k_steps, "mlc": leaves(edge)}]
    return [linac(jaws_mm=[-50, 50, -20, 20], weight=mu, control_points=cps,
                  mlc={"boundaries_mm": bnd})]
